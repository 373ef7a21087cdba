"""What refiners do to the poses of the parts the inference path found (a diagnostic).

BOP 6D AP (``python -m infer bop --evaluate``) is the figure that leads; it mixes detection
and pose. This script isolates the refiner: the same initial poses (a results CSV of ``infer
bop`` without a refiner) refined by each refiner (``infer bop --refine-only INITIAL.csv
--refiner ...``, which keeps the rows in order), and for every initial estimate that lies
within ``--within`` mm of a ground-truth instance of its own part in its image (the parts
found; the nearest instance is its truth), the rotation error (degrees, the smallest over the
part's symmetries, ``threept_jax.geometry.symmetry.symmetric_angle_deg``) and the translation
error (mm) before and after each refiner. The reference is the initial poses, in the same run.

    python bench/refine_found.py --dataset-dir D --split val_pbr INITIAL.csv REFINED.csv...
"""

from __future__ import annotations

import argparse
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from threept_jax.data.bop.reader import BopDataset  # noqa: E402
from threept_jax.data.bop.results import read_pose_results  # noqa: E402
from threept_jax.geometry.symmetry import symmetric_angle_deg, symmetry_transforms  # noqa: E402


def found(dataset: BopDataset, split: str, initial, within: float):
    """[(row, R_gt, t_gt, obj_id)] of the initial estimates within ``within`` mm of a
    ground-truth instance of their part in their image."""
    split_ = dataset.split(split)
    gts = {}
    for scene_id in split_.scene_ids:
        for im_id, insts in split_.scene(scene_id).gt.items():
            gts[scene_id, im_id] = insts
    out = []
    for i, e in enumerate(initial):
        cands = [g for g in gts.get((e.scene_id, e.im_id), []) if g.obj_id == e.obj_id]
        if not cands:
            continue
        d = [np.linalg.norm(e.t - g.T_cam_obj[:3, 3]) for g in cands]
        j = int(np.argmin(d))
        if d[j] <= within:
            out.append((i, cands[j].T_cam_obj[:3, :3], cands[j].T_cam_obj[:3, 3], e.obj_id))
    return out


def errors(estimates, matched, syms) -> np.ndarray:
    """[N, 2]: rotation (deg, symmetry-aware) and translation (mm) errors of ``estimates``'
    rows in ``matched``."""
    rows = []
    for i, R_gt, t_gt, obj_id in matched:
        e = estimates[i]
        rot = symmetric_angle_deg(e.R[None], R_gt[None], syms[obj_id])[0]
        rows.append((rot, np.linalg.norm(e.t - t_gt)))
    return np.asarray(rows).reshape(-1, 2)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--dataset-dir", type=pathlib.Path, required=True)
    p.add_argument("--split", default="val_pbr")
    p.add_argument("--within", type=float, default=30.0,
                   help="mm from a ground-truth instance of its part for an estimate to count")
    p.add_argument("initial", type=pathlib.Path, help="results CSV of infer bop, no refiner")
    p.add_argument("refined", type=pathlib.Path, nargs="+",
                   help="results CSVs of infer bop --refine-only INITIAL")
    args = p.parse_args(argv)
    dataset = BopDataset(args.dataset_dir)
    syms = {k: symmetry_transforms(m.symmetries)[0] for k, m in dataset.models().items()}
    initial = read_pose_results(args.initial)
    matched = found(dataset, args.split, initial, args.within)
    if not matched:
        raise SystemExit(f"no estimate of {args.initial} lies within {args.within:g} mm of its "
                         "part: nothing to compare")
    print(f"{len(matched)} of {len(initial)} estimates within {args.within:g} mm of their part")
    start = np.median(errors(initial, matched, syms)[:, 1])
    for path in [args.initial, *args.refined]:
        est = read_pose_results(path)
        if len(est) != len(initial) or any(
                (a.scene_id, a.im_id, a.obj_id) != (b.scene_id, b.im_id, b.obj_id)
                for a, b in zip(est, initial, strict=True)):
            raise SystemExit(f"{path} does not hold {args.initial}'s rows in order: pass the "
                             "output of infer bop --refine-only with it")
        err = errors(est, matched, syms)
        rot, trans = err[:, 0], err[:, 1]
        print(f"{path}: rotation median {np.median(rot):.2f} deg (< 5 deg {np.mean(rot < 5):.2f},"
              f" < 10 deg {np.mean(rot < 10):.2f}), translation median {np.median(trans):.2f} mm"
              f" ({np.median(trans) / start:.3f} x the "
              "initial)")


if __name__ == "__main__":
    main()
