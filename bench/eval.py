"""Benchmark: BOP 6D evaluation of 1000 images x 10 objects.

Builds a synthetic BOP dataset (10 shared BOP meshes from ../shared/meshes/bop, or procedural
meshes when absent; 20 scenes x 50 images, every object once per image), writes a results CSV
with one perturbed estimate per GT and 3 false positives per image, and times
`threept_jax.eval.evaluate_pose_results` (AP, AP-mm, AR over MSSD and MSPD). The reference is a
straightforward per-estimate NumPy loop in the toolkit's style (every symmetry, every vertex,
one pair at a time) timed on a sample of pairs per object and extrapolated to all pairs.

    python bench/eval.py [--images 1000] [--seed 0]
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib
import sys
import tempfile
import time

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from threept_jax.data import bop  # noqa: E402
from threept_jax.eval.bop_eval import evaluate_pose_results  # noqa: E402
from threept_jax.geometry.symmetry import Symmetries, symmetry_transforms  # noqa: E402
from threept_jax.testing.bop_synthetic import SyntheticInstance, write_synthetic_dataset  # noqa: E402

SHARED = ROOT.parent / "shared" / "meshes" / "bop"
# (dataset, obj_id): T-LESS with a continuous and with discrete symmetries, large YCB-V, IC-BIN
# and T-LESS meshes (20-44k vertices), small ITODD ones.
PICKS = [
    ("tless", 4),
    ("tless", 5),
    ("tless", 11),
    ("tless", 27),
    ("ycbv", 14),
    ("ycbv", 1),
    ("icbin", 2),
    ("itodd", 14),
    ("itodd", 6),
    ("tudl", 3),
]
K = np.array([[1075.65, 0.0, 320.0], [0.0, 1073.9, 240.0], [0.0, 0.0, 1.0]])


def load_meshes(tmp: pathlib.Path) -> dict[int, bop.ObjectModel]:
    models = {}
    if all((SHARED / d / "models" / f"obj_{o:06d}.ply").is_file() for d, o in PICKS):
        for new_id, (d, o) in enumerate(PICKS, start=1):
            m = bop.load_models(SHARED / d / "models")[o]
            models[new_id] = dataclasses.replace(m, obj_id=new_id)
        return models
    import trimesh

    print("shared meshes not found: using procedural meshes")
    for new_id in range(1, 11):
        mesh = trimesh.creation.icosphere(subdivisions=5)
        mesh.apply_scale([40 + 5 * new_id, 30, 20 + 3 * new_id])
        path = tmp / f"proc_{new_id}.ply"
        path.write_bytes(trimesh.exchange.ply.export_ply(mesh, encoding="ascii"))
        syms = (
            Symmetries(discrete=[np.diag([-1.0, -1.0, 1.0, 1.0])])
            if new_id % 3 == 0
            else Symmetries()
        )
        models[new_id] = bop.compute_model_info(mesh.vertices, syms, new_id, path)
    return models


def make_case(root: pathlib.Path, models, n_images: int, seed: int):
    rng = np.random.default_rng(seed)
    per_scene = 50
    scenes, ests = {}, []
    for im in range(n_images):
        sid, iid = im // per_scene, im % per_scene
        insts = []
        for k, obj in enumerate(models):
            T = np.eye(4)
            T[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
            T[:3, 3] = [-300 + 150 * (k % 5), -100 + 200 * (k // 5), rng.uniform(900, 1300)]
            insts.append(SyntheticInstance(obj, T, float(rng.uniform(0.05, 1.0))))
            Te = T.copy()
            Te[:3, :3] = Te[:3, :3] @ Rotation.from_rotvec(rng.normal(size=3) * 0.03).as_matrix()
            Te[:3, 3] += rng.normal(size=3) * 3.0
            ests.append(
                bop.PoseEstimate(sid, iid, obj, float(rng.random()), Te[:3, :3], Te[:3, 3], 0.5)
            )
        for _ in range(3):
            obj = int(rng.integers(1, len(models) + 1))
            R = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
            ests.append(
                bop.PoseEstimate(
                    sid,
                    iid,
                    obj,
                    float(rng.random()),
                    R,
                    [rng.uniform(-300, 300), rng.uniform(-150, 150), 1100],
                    0.5,
                )
            )
        scenes.setdefault(sid, {})[iid] = insts
    write_synthetic_dataset(root, models, scenes, K, 640, 480, write_images=False)
    csv = root / "bench_synth-test.csv"
    bop.write_pose_results(csv, ests)
    return csv, scenes, ests


def reference_seconds(models, scenes, ests, per_object: int = 3) -> float:
    """Toolkit-style loop (`pose_error.mssd` / `mspd`: per pair, per symmetry, all vertices),
    timed on ``per_object`` pairs per object and extrapolated to all (estimate, GT) pairs."""
    gt = {}
    for sid, ims in scenes.items():
        for iid, insts in ims.items():
            for inst in insts:
                gt[(sid, iid, inst.obj_id)] = inst.T_cam_obj
    pairs: dict[int, list] = {}
    for e in ests:
        pairs.setdefault(e.obj_id, []).append((e, gt[(e.scene_id, e.im_id, e.obj_id)]))
    total = 0.0
    for obj, ps in pairs.items():
        pts = models[obj].vertices()
        Rs, ts = symmetry_transforms(models[obj].symmetries)
        t0 = time.perf_counter()
        for e, T in ps[:per_object]:
            pe = pts @ e.R.T + e.t
            ue = pe @ K.T
            ue = ue[:, :2] / ue[:, 2:]
            best_s = best_p = np.inf
            for R, t in zip(Rs, ts):
                pg = pts @ (T[:3, :3] @ R).T + (T[:3, :3] @ t + T[:3, 3])
                best_s = min(best_s, np.linalg.norm(pe - pg, axis=1).max())
                ug = pg @ K.T
                best_p = min(best_p, np.linalg.norm(ue - ug[:, :2] / ug[:, 2:], axis=1).max())
        dt = (time.perf_counter() - t0) / min(per_object, len(ps))
        total += dt * len(ps)
    return total


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--images", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        models = load_meshes(tmp)
        t0 = time.perf_counter()
        csv, scenes, ests = make_case(tmp / "synth", models, args.images, args.seed)
        print(
            f"dataset: {args.images} images x {len(models)} objects, {len(ests)} estimates "
            f"(written in {time.perf_counter() - t0:.1f} s)"
        )
        times = []
        for run in ("first", "second"):
            t0 = time.perf_counter()
            scores = evaluate_pose_results(tmp / "synth", bop.read_pose_results(csv))
            times.append(time.perf_counter() - t0)
            print(
                f"{run} run (reads CSV, scene JSON and meshes): {times[-1]:.1f} s   "
                f"AP {scores.ap:.4f}  AP_MSSD {scores.ap_mssd:.4f}  AP_MSPD {scores.ap_mspd:.4f}  "
                f"AP-mm {scores.ap_mm:.4f}  AR_MSSD {scores.ar_mssd:.4f}  "
                f"AR_MSPD {scores.ar_mspd:.4f}"
            )
        ref = reference_seconds(models, scenes, ests)
        print(f"reference per-pair NumPy loop (MSSD + MSPD only, extrapolated): {ref:.0f} s")
        print(
            f"evaluation: {min(times):.1f} s for {args.images} images; "
            f"{ref / min(times):.0f}x faster than the reference"
        )


if __name__ == "__main__":
    main()
