"""Benchmark of the 3PT-R train step: compile time, step time, examples/s, renders/s and MFU.

Runs the refiner trainer's real step (``train.trainer_refiner.make_train_step``: renders of
every hypothesis inside the jitted step, one forward pass, the three losses, the classification
target's refinement step under ``stop_gradient``, AdamW) on synthetic but valid batches, over a
mesh of all local devices:

* cold: ``lower`` + ``compile`` time, and the first call;
* warm: mean step time over ``--steps`` calls, examples/s (an example is one instance with
  J = ``data.num_hypotheses`` hypotheses in V = 1 view);
* renders: the step renders B x J x V hypotheses per call (colour at the crop size, object
  coordinates, mask and edges at the map size); a jitted :func:`train.refiner_objective.
  render_batch` alone on the same batch gives renders/s and the share of the step spent
  rendering (warm render time / warm step time, both means over ``--steps`` calls);
* FLOPs per step from XLA's cost analysis of the compiled step (an analytic count of the ViT
  encoder over the real crops and the renders, x 3 for forward + backward, is printed beside
  it as a cross-check; it leaves out cross-attention, DPT, rendering and PnP), achieved FLOP/s
  and the **ratio** against a plain matmul's FLOP/s measured in the same process (float32 on
  CPU, bfloat16 on GPU), as ``bench/train_step.py`` does; the MFU against the device's peak
  dense bf16 FLOP/s too on a known GPU.

Batches: the T-LESS CAD models obj 4-7 (``../shared/meshes/bop/tless/models``) prepared as the
trainer prepares them (``prepare_mesh``, ``refine.max_faces``) and stacked with
``RefinerMeshes.from_meshes``; ground-truth poses at random rotations 3-5 diameters in front of
the camera, hypotheses drawn by the data pipeline's own noise (``perturb_poses``) and crops cut
around the first one (``crop_boxes``), so every render shows the object (checked before
timing); random uint8 crops, a disc as the visible mask, identity symmetries.

Data (``--records DIR``, issue 40 item 3): the training pipeline's real side
(:func:`threept_jax.data.refiner_input.refiner_dataset` over DIR's train split at the variant's
example config: decoding, sampling an instance, perturbing its hypotheses, cutting its crop)
timed in this process on one thread, against what the warm step consumes: the ratio says
how many data workers feed the step (the device's goal: 1.2 x what it consumes).

Variants are the configs of ``train/configs/refiner.py``: ``tiny`` and ``cpu`` everywhere, plus
``small`` when an accelerator is present; the batch is the config's ``batch_size``.
``python bench/refiner_step.py [--variants tiny cpu] [--steps 5] [--batch N] [--records DIR]``.
"""

from __future__ import annotations

import argparse
import functools
import pathlib
import sys
import time
import warnings

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
from flops import cost_flops, matmul_reference, mfu_note, vit_forward_flops  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from threept_jax.data.detector_input import pad_symmetries  # noqa: E402
from threept_jax.data.refiner_input import (  # noqa: E402
    RefinerExampleConfig,
    RefinerMeshes,
    perturb_poses,
    refiner_dataset,
)
from threept_jax.geometry.camera import crop_intrinsics  # noqa: E402
from threept_jax.geometry.framing import crop_boxes  # noqa: E402
from threept_jax.models.configs import REFINER_SIZES, RefinerConfig  # noqa: E402
from threept_jax.render.mesh import Mesh, load_mesh, prepare_mesh  # noqa: E402
from train import sharding  # noqa: E402
from train.configs import refiner as refiner_configs  # noqa: E402
from train.refiner_objective import RefinerAssets, render_batch  # noqa: E402
from train.run_config import (  # noqa: E402
    model_config,
    refine_settings,
    refiner_example_config,
)
from train.trainer_refiner import build_step  # noqa: E402

MODELS = ROOT.parent / "shared" / "meshes" / "bop" / "tless" / "models"
OBJ_IDS = (4, 5, 6, 7)
#: Full-image intrinsics the crops are cut from (a 640 x 480 camera).
K_IMAGE = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])


def load_meshes(max_faces: int, models: pathlib.Path = MODELS) -> dict[int, Mesh]:
    """{obj_id: prepared mesh} of the benchmark's T-LESS models in ``models`` (as
    ``RefinerMeshes.from_records`` prepares them)."""
    out = {}
    for obj_id in OBJ_IDS:
        path = models / f"obj_{obj_id:06d}.ply"
        if not path.is_file():
            raise FileNotFoundError(f"benchmark mesh {path} not found; the bench reads the "
                                    f"T-LESS models obj {OBJ_IDS} from {models} (--models)")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out[obj_id] = prepare_mesh(load_mesh(path, models_info=None), max_faces=max_faces,
                                       texture_size=None)
    return out


def synthetic_batch(rng: np.random.Generator, meshes: list[Mesh], batch: int,
                    cfg: RefinerExampleConfig) -> dict[str, np.ndarray]:
    """The step's fields (``STEP_FIELDS``) of ``batch`` valid single-view examples (module
    docstring); example b shows ``meshes[b % len(meshes)]``, row b % O of the stacked meshes."""
    J, S, m = cfg.num_hypotheses, cfg.crop_size, cfg.output_size
    hyps, gts, crop_Ks = [], [], []
    for b in range(batch):
        mesh = meshes[b % len(meshes)]
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        c_cam = np.array([*rng.uniform(-0.3, 0.3, 2), 1.0]) * rng.uniform(3, 5) * mesh.diameter
        T[:3, 3] = c_cam - T[:3, :3] @ mesh.center
        h = perturb_poses(T, mesh.center, mesh.diameter, J, cfg, rng)
        box = np.asarray(crop_boxes(mesh, h[0], np.eye(4)[None], K_IMAGE[None],
                                    margin=cfg.crop_margin))[0]
        crop_Ks.append(np.asarray(crop_intrinsics(K_IMAGE, box, (S, S))))
        hyps.append(h)
        gts.append(T)
    ij = (np.arange(m) + 0.5) / m - 0.5
    disc = np.hypot(ij[:, None], ij[None, :]) < 0.35
    sym, sym_mask = pad_symmetries(np.eye(4, dtype=np.float32)[None], cfg.max_symmetries)
    return {
        "crops": rng.integers(0, 256, (batch, 1, S, S, 3), dtype=np.uint8),
        "crop_K": np.asarray(crop_Ks, np.float32)[:, None],
        "T_cam_world": np.tile(np.eye(4, dtype=np.float32), (batch, 1, 1, 1)),
        "T_world_obj_gt": np.asarray(gts, np.float32),
        "hypotheses": np.asarray(hyps, np.float32),
        "visible_mask": np.broadcast_to(disc, (batch, 1, m, m)).copy(),
        "mesh_index": (np.arange(batch) % len(meshes)).astype(np.int32),
        "symmetries": np.broadcast_to(sym, (batch, *sym.shape)).copy(),
        "symmetry_mask": np.broadcast_to(sym_mask, (batch, *sym_mask.shape)).copy(),
        "valid": np.ones(batch, bool),
    }


def encoder_train_flops(cfg: RefinerConfig, batch: int, num_hyp: int, views: int = 1) -> float:
    """Analytic FLOPs of the ViT encoder in one step: 3 x the forward FLOPs (forward +
    backward) over the B V real crops and the B J V renders, each (crop / patch)^2 patch tokens
    plus the registers (:func:`flops.vit_forward_flops`)."""
    tokens = (cfg.crop_size // cfg.patch_size) ** 2 + cfg.num_registers
    return 3.0 * batch * views * (1 + num_hyp) * vit_forward_flops(cfg.variant, tokens)


def timed(call, steps: int) -> tuple[float, float, object]:
    """(seconds of the first call, mean seconds of ``steps`` more, the first call's output);
    ``call`` returns device arrays, waited for."""
    t0 = time.perf_counter()
    first = jax.block_until_ready(call())
    cold = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(steps):
        out = call()
    jax.block_until_ready(out)
    return cold, (time.perf_counter() - t0) / steps, first


def bench_variant(variant: str, steps: int, batch_override: int | None,
                  models: pathlib.Path = MODELS) -> dict:
    config = refiner_configs.get_config(variant)
    mesh = sharding.make_mesh(-1, 1)
    batch = batch_override or int(config.batch_size)
    batch = max(batch // mesh.devices.size, 1) * mesh.devices.size
    model_cfg = model_config(config)
    ex_cfg = refiner_example_config(config)
    settings = refine_settings(config)
    prepared = load_meshes(int(config.refine.max_faces), models)
    meshes = RefinerMeshes.from_meshes(prepared)
    assets = RefinerAssets.from_meshes(meshes)
    host = synthetic_batch(np.random.default_rng(0), [prepared[k] for k in meshes.obj_ids],
                           batch, ex_cfg)
    device_batch = sharding.global_batch(host, mesh)
    replicated = sharding.replicated(mesh)
    placed = jax.device_put(assets, replicated)

    # The renders alone, as the step makes them.
    render = jax.jit(functools.partial(render_batch, crop_size=model_cfg.crop_size,
                                       output_size=model_cfg.output_size,
                                       ambient=settings.ambient))
    _, render_s, rend = timed(lambda: render(placed, device_batch), steps)
    pixels = np.asarray(rend.mask).sum(axis=(-2, -1))  # [B, J, V]
    if not (pixels > 0).all():
        raise RuntimeError(f"{int((pixels == 0).sum())} of {pixels.size} hypothesis renders are "
                           "empty: the synthetic poses do not put the object in its crop")
    coverage = float(pixels.mean()) / model_cfg.output_size**2

    # The trainer's own jitted step (train.trainer.compile_step), compiled ahead of time.
    built = build_step(config, assets, mesh)
    placed = built.assets
    state = built.init()
    jax.block_until_ready(state)
    t0 = time.perf_counter()
    compiled = built.jitted.lower(state, device_batch, placed).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    state, metrics = compiled(state, device_batch, placed)
    jax.block_until_ready(metrics)
    first_s = time.perf_counter() - t0
    if not np.isfinite(float(metrics["loss"])):
        raise RuntimeError(f"{variant}: the step's loss is not finite: {float(metrics['loss'])}")
    t0 = time.perf_counter()
    for _ in range(steps):
        state, metrics = compiled(state, device_batch, placed)
    jax.block_until_ready(metrics)
    step_s = (time.perf_counter() - t0) / steps

    num_hyp = int(ex_cfg.num_hypotheses)
    return dict(variant=variant, batch=batch, num_hyp=num_hyp, vit=model_cfg.variant,
                crop=model_cfg.crop_size, map=model_cfg.output_size,
                faces=meshes.face_budget, dtype=np.dtype(model_cfg.dtype).name,
                compile_s=compile_s, first_s=first_s, step_s=step_s,
                examples_per_s=batch / step_s, renders=batch * num_hyp,
                render_s=render_s, coverage=coverage,
                flops=cost_flops(compiled),
                analytic=encoder_train_flops(model_cfg, batch, num_hyp))


def data_rate(records: pathlib.Path, variant: str, examples: int) -> float:
    """Examples/s one thread of this process makes from ``records``' train split at
    ``variant``'s example config (the first 2 examples, which open the files, are not
    timed)."""
    ds = refiner_dataset(records, "train", refiner_example_config(
        refiner_configs.get_config(variant)), seed=0, batch_size=None)
    for i in range(2):
        ds[i]
    t0 = time.perf_counter()
    for i in range(2, 2 + examples):
        ds[i]
    return examples / (time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", nargs="*", default=None, choices=list(REFINER_SIZES),
                        help="configs of train/configs/refiner.py (default: tiny cpu, plus "
                             "small on an accelerator)")
    parser.add_argument("--steps", type=int, default=5, help="warm steps to average")
    parser.add_argument("--batch", type=int, default=None,
                        help="override the batch size (default: the config's batch_size)")
    parser.add_argument("--models", type=pathlib.Path, default=MODELS,
                        help="folder of the T-LESS models obj 4-7 (default: ../shared's)")
    parser.add_argument("--records", type=pathlib.Path, default=None,
                        help="a records folder: also time the training data's real side "
                             "against the step (module docstring)")
    parser.add_argument("--data-examples", type=int, default=64,
                        help="examples timed with --records")
    args = parser.parse_args()
    if args.records is not None and not (args.records / "objects.json").is_file():
        parser.error(f"--records {args.records} is not a records folder (no objects.json): "
                     "pass a train.adapt, campaign or datagen.pack output")
    if args.steps < 1:
        parser.error(f"--steps must be >= 1, got {args.steps}")
    if args.batch is not None and args.batch < 1:
        parser.error(f"--batch must be >= 1, got {args.batch}")
    accel, ref = matmul_reference()
    variants = args.variants or (["tiny", "cpu", "small"] if accel else ["tiny", "cpu"])
    for v in variants:
        try:
            r = bench_variant(v, args.steps, args.batch, args.models)
        except (FileNotFoundError, RuntimeError) as e:
            print(f"error: {e}", file=sys.stderr)
            sys.exit(2)
        flops = r["flops"] if r["flops"] else r["analytic"]
        achieved = flops / r["step_s"]
        src = "XLA cost analysis" if r["flops"] else "analytic count"
        line = (f"{v}: batch {r['batch']} x {r['num_hyp']} hypotheses x 1 view ({r['vit']}, "
                f"{r['crop']} px crops, {r['map']} px maps, {r['faces']} faces, {r['dtype']}): "
                f"cold compile {r['compile_s']:.1f} s, first step {r['first_s']:.2f} s; warm "
                f"step {r['step_s'] * 1e3:.1f} ms, {r['examples_per_s']:.3g} examples/s; "
                f"renders {r['renders'] / r['render_s']:.3g}/s ({r['renders']} per step, "
                f"{r['render_s'] * 1e3:.1f} ms = {r['render_s'] / r['step_s']:.0%} of the step, "
                f"mask {r['coverage']:.0%} of the map); {flops / 1e9:.2f} GFLOP/step ({src}; "
                f"analytic encoder count {r['analytic'] / 1e9:.2f}), "
                f"{achieved / 1e9:.1f} GFLOP/s = {achieved / ref:.3f} x the matmul reference")
        print(line + mfu_note(achieved), flush=True)
        if args.records is not None:
            made = data_rate(args.records, v, args.data_examples)
            workers = int(np.ceil(1.2 * r["examples_per_s"] / made))
            print(f"{v} data: one thread makes {made:.3g} examples/s from {args.records} = "
                  f"{made / r['examples_per_s']:.3f} x what the step consumes "
                  f"({r['examples_per_s']:.3g}/s); {workers} data worker"
                  f"{'s' if workers > 1 else ''} feed it 1.2 x", flush=True)


if __name__ == "__main__":
    main()
