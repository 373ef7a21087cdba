"""3PT-R training configs: ``get_config("tiny" | "cpu" | "small" | "paper")``.

Used as ``python train/launch.py --config train/configs/refiner.py:tiny --workdir DIR
--config.data_dir=RECORDS [--config.eval.data_dir=HELD_OUT_RECORDS] [--config.key=value ...]``.
The configs state only overrides of :func:`train.run_config.default_config` for the
``"refiner"`` trainer (``model`` is a ``RefinerConfig``, ``loss`` a ``RefinerLossConfig``,
``data`` a ``RefinerExampleConfig`` plus the input settings, ``refine`` the refinement step's
``RefineSettings``, ``eval`` a ``RefinerEvalConfig``); a key outside that schema is refused.
``data_dir``: a records folder written by ``python -m datagen.pack`` (its ``objects.json`` rows
carry the meshes); ``eval.data_dir``: records of objects training never saw (default: the val
split of ``data_dir``).

The model sizes are ``threept_jax.models.configs.REFINER_SIZES``:

* ``tiny``: CPU, tests and the demo: the "tiny/16" ViT, 64 px crops, 32 x 32 maps, batch 8
  instances x 5 hypotheses, meshes decimated to 1024 faces.
* ``cpu``: the best refiner 2 CPU cores train in an hour: "mini/16", 64 px crops, batch 8.
* ``small``: one GPU: S/14 on 224 px crops, 64 x 64 maps, batch 64, bf16.
* ``paper``: L/14 with registers, 224 px crops, bf16, rematerialised, 64 instances per device
  (``Refiner.memory_plan``), FSDP over 8 devices.
"""

from __future__ import annotations

import ml_collections

from threept_jax.models.configs import REFINER_SIZES
from train.run_config import default_config


def get_config(arg: str = "tiny") -> ml_collections.ConfigDict:
    """``"tiny"``, ``"cpu"``, ``"small"`` or ``"paper"`` (module docstring)."""
    if arg not in REFINER_SIZES:
        raise ValueError(f"unknown refiner config {arg!r}; use {', '.join(REFINER_SIZES)} "
                         "(train/configs/refiner.py:tiny)")
    c = default_config("refiner")
    c.model.update(REFINER_SIZES[arg])
    if "dtype" not in REFINER_SIZES[arg]:
        c.model.dtype = "auto"  # bfloat16 on accelerators, float32 on CPU
    c.checkpoint.best_metric = "eval/ar_mssd_after"
    c.checkpoint.best_mode = "max"
    # The sub-pixel fit of matched 3D points assumes a descriptor similarity peaked in 3D
    # distance: exact for the oracle (whose tests need it for sub-millimetre poses), but with a
    # trained tiny refiner (800 CPU steps) it lowered held-out MSSD recall after 3 steps from
    # 0.41 (off) to 0.29 (on) (docs/benchmarks.md, "Refiner training (CPU)").
    c.refine.subpixel = False
    if arg in ("tiny", "cpu"):
        c.total_steps = 1000 if arg == "tiny" else 6000
        c.batch_size = 8
        c.refine.update(num_matches=64, max_faces=1024)
        c.optim.update(learning_rate=1e-3, warmup_steps=50)
        c.eval.update(every_steps=200 if arg == "tiny" else 1000, num_examples=32, batch_size=8)
        c.checkpoint.every_steps = c.eval.every_steps
        c.log_every = 20 if arg == "tiny" else 100
    elif arg == "small":
        c.total_steps = 20_000
        c.batch_size = 64
        c.data.num_workers = 8
        c.refine.num_matches = 256
        c.optim.update(learning_rate=4e-4, warmup_steps=1000)
        c.eval.update(every_steps=2000, num_examples=256, batch_size=64)
        c.checkpoint.every_steps = 1000
        c.log_every = 100
    else:  # paper
        c.total_steps = 200_000
        c.batch_size = 64 * 64
        c.data.update(num_workers=16, worker_buffer_size=4)
        c.refine.num_matches = 512
        c.optim.update(learning_rate=2e-4, warmup_steps=10_000, weight_decay=0.05)
        c.eval.update(every_steps=10_000, num_examples=2048, batch_size=512)
        c.checkpoint.update(every_steps=2000, max_to_keep=3)
        c.mesh.update(data=-1, fsdp=8)
        c.log_every = 100
    return c
