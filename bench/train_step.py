"""Benchmark of the 3PT-D train step: compile time, step time, examples/s and an MFU figure.

Runs the trainer's real step (``train.trainer_detector``: object tower on the 12 prior renders
and the sampled templates, image tower, Hungarian matching on the host, AdamW) on synthetic
batches of the right shapes, over a mesh of all local devices:

* cold: ``lower`` + ``compile`` time, and the first call;
* warm: mean step time over ``--steps`` calls, examples/s;
* FLOPs per step from XLA's cost analysis of the compiled step (an analytic ViT count is
  printed beside it as a cross-check), achieved FLOP/s, and the **ratio** against a plain
  matmul's FLOP/s measured in the same process on the same device (float32 on CPU, bfloat16
  on GPU): an MFU-style figure that needs no datasheet. On GPU the MFU against the device's
  peak dense bf16 FLOP/s is printed too when the device is known (H100: 989 TFLOP/s,
  H200: 989 TFLOP/s).

Variants: ``tiny`` and ``mini/16`` (the ``cpu`` config; 128 px tiles, 32 px renders) and
``S/16`` (512 px tiles, 112 px renders) everywhere; ``B/16`` (512 px, 224 px renders, bf16,
remat) when an accelerator is present.
``python bench/train_step.py [--variants tiny S/16] [--steps 5]``.
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np
from flops import cost_flops, matmul_reference, mfu_note, vit_forward_flops

from threept_jax.losses.detection import DetectorLossConfig
from threept_jax.models.configs import DetectorConfig
from train import sharding
from train import trainer_detector as td
from train.configs import detector as detector_configs

#: variant -> (tile, render, templates per example, max instances, batch on CPU, on GPU)
SETUPS = {
    "tiny": (128, 32, 16, 8, 8, 256),
    "mini/16": (128, 32, 32, 8, 16, 64),  # the cpu config: the shipped detector
    "S/16": (512, 112, 16, 16, 2, 64),
    "B/16": (512, 224, 64, 32, 1, 32),
}


def synthetic_batch(rng: np.random.Generator, batch: int, tile: int, render: int,
                    num_templates: int, max_instances: int) -> dict[str, np.ndarray]:
    """A batch with the pipeline's shapes: random images, 1..M boxes of 64-256 px (scaled)."""
    m = max_instances
    size = rng.uniform(0.12, 0.5, (batch, m, 1)) * tile
    xy = rng.uniform(0, 1, (batch, m, 2)) * (tile - size)
    boxes = np.concatenate([xy, xy + size], -1).astype(np.float32)
    count = rng.integers(1, m + 1, batch)
    mask = np.arange(m)[None] < count[:, None]
    return {
        "image": rng.integers(0, 256, (batch, tile, tile, 3), dtype=np.uint8),
        "prior_rgb": rng.integers(0, 256, (batch, 12, render, render, 3), dtype=np.uint8),
        "template_rgb": rng.integers(0, 256, (batch, num_templates, render, render, 3),
                                     dtype=np.uint8),
        "template_rotations": np.tile(np.eye(3, dtype=np.float32),
                                      (batch, num_templates, 1, 1)),
        "template_index": rng.integers(0, num_templates, (batch, m)).astype(np.int32),
        "boxes": boxes,
        "mask": mask,
        "rotations": np.tile(np.eye(3, dtype=np.float32), (batch, m, 1, 1)),
    }


def vit_train_flops(cfg: DetectorConfig, batch: int, num_templates: int) -> float:
    """Analytic FLOPs of one step: 3 x the ViT forward FLOPs (forward + backward) over every
    image of the batch (the tile with its prior tokens, 12 priors and the templates); the
    forward count is :func:`flops.vit_forward_flops`."""
    p = cfg.patch_size
    image_tokens = (cfg.image_size // p) ** 2 + cfg.num_prior_tokens
    render_tokens = (cfg.render_size // p) ** 2
    per_example = (vit_forward_flops(cfg.variant, image_tokens)
                   + (12 + num_templates) * vit_forward_flops(cfg.variant, render_tokens))
    return 3.0 * batch * per_example


def bench_variant(variant: str, steps: int, accel: bool, batch_override: int | None) -> dict:
    tile, render, num_t, max_inst, b_cpu, b_gpu = SETUPS[variant]
    batch = batch_override or (b_gpu if accel else b_cpu)
    mesh = sharding.make_mesh(-1, 1)
    batch = max(batch // mesh.devices.size, 1) * mesh.devices.size
    config = detector_configs.get_config("tiny")
    config.model.update(variant=variant, image_size=tile, render_size=render,
                        remat=variant == "B/16" and accel)
    model_cfg = td.model_config(config)
    loss_cfg = DetectorLossConfig()
    compiled_step = td.build_step(model_cfg, loss_cfg, config.optim, 1000, 0, mesh,
                                      config.mesh.fsdp_min_size)
    host = synthetic_batch(np.random.default_rng(0), batch, tile, render, num_t, max_inst)
    device_batch = sharding.global_batch(host, mesh)
    state = compiled_step.init()
    jax.block_until_ready(state)

    t0 = time.perf_counter()
    compiled = compiled_step.step.lower(state, device_batch).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    state, metrics = compiled(state, device_batch)
    jax.block_until_ready(metrics)
    first_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(steps):
        state, metrics = compiled(state, device_batch)
    jax.block_until_ready(metrics)
    step_s = (time.perf_counter() - t0) / steps
    flops = cost_flops(compiled)
    analytic = vit_train_flops(model_cfg, batch, num_t)
    return dict(variant=variant, batch=batch, tile=tile, render=render, templates=num_t,
                dtype=str(model_cfg.dtype), compile_s=compile_s, first_s=first_s,
                step_s=step_s, examples_per_s=batch / step_s, flops=flops, analytic=analytic)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", nargs="*", default=None,
                        help="default: tiny S/16, plus B/16 on an accelerator")
    parser.add_argument("--steps", type=int, default=5, help="warm steps to average")
    parser.add_argument("--batch", type=int, default=None, help="override the batch size")
    args = parser.parse_args()
    accel, ref = matmul_reference()
    variants = args.variants or (["tiny", "S/16", "B/16"] if accel else ["tiny", "S/16"])
    for v in variants:
        r = bench_variant(v, args.steps, accel, args.batch)
        flops = r["flops"] if r["flops"] else r["analytic"]
        achieved = flops / r["step_s"]
        src = "XLA cost analysis" if r["flops"] else "analytic count"
        line = (f"{v}: batch {r['batch']} ({r['tile']} px tiles, {r['render']} px renders, "
                f"{r['templates']} templates, {r['dtype']}): cold compile {r['compile_s']:.1f} s, "
                f"first step {r['first_s']:.2f} s; warm step {r['step_s'] * 1e3:.1f} ms, "
                f"{r['examples_per_s']:.3g} examples/s; {flops / 1e9:.1f} GFLOP/step ({src}; "
                f"analytic ViT count {r['analytic'] / 1e9:.1f}), {achieved / 1e9:.1f} GFLOP/s "
                f"= {achieved / ref:.2f} x the matmul reference")
        print(line + mfu_note(achieved), flush=True)


if __name__ == "__main__":
    main()
