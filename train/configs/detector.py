"""3PT-D training configs: ``get_config("tiny" | "cpu" | "small" | "paper")``.

Used as ``python train/launch.py --config train/configs/detector.py:tiny --workdir DIR
[--config.key=value ...]``. The configs state only overrides of the defaults of
:func:`train.run_config.default_config` (every key of the schema, from the dataclass owning
it: ``model`` is a ``DetectorConfig``, ``loss`` a ``DetectorLossConfig``, ...); a key outside
that schema is refused. Top-level ``total_steps``, ``batch_size`` (global, over all processes
and devices) and ``data_dir`` (a records folder with ``train/`` and ``val/`` ArrayRecord
shards, ``objects.json`` and ``banks/``, written by ``python -m datagen.pack``).

* ``tiny``: CPU, tests and the demo: 128 px tiles, the "tiny/16" ViT (width 64, depth 2),
  32 px renders, 16 templates per example, batch 16, 1000 steps (about 4 minutes on 2 cores),
  one-to-many matching (4 positives per object).
* ``cpu``: the best detector 2 CPU cores train in 30-60 minutes (docs/training.md, "CPU
  recipes"): the "mini/16" ViT (width 128, depth 4) on 128 px tiles, 32 px renders, 32
  templates per example, batch 16; ``python -m train.adapt`` sets the steps from its
  ``--minutes``.
* ``small``: one GPU in under an hour: S/16 on 512 px tiles, 112 px renders, batch 64,
  64 templates per example, 20k steps.
* ``paper``: the paper's sizes and data scale (docs/design.md section 1.1): B/16 on 512 px tiles,
  224 px renders, the 5140-template bank (128 sampled per example in a step, the whole bank
  at evaluation), global batch 4096 over many hosts with FSDP, 250k steps (~1B image-render
  pairs: 4096 tiles x 250k steps, each with 12 prior + 128 template renders).
"""

from __future__ import annotations

import ml_collections

from train.run_config import default_config


def _base() -> ml_collections.ConfigDict:
    """The overrides every variant shares; every other key keeps its dataclass default
    (``train/run_config.py`` names the dataclass of each section)."""
    c = default_config()
    c.model.update(
        variant="tiny/16",
        image_size=128,  # the tile side, also the data pipeline's tile
        render_size=32,
        dtype="auto",  # bfloat16 on accelerators, float32 on CPU
    )
    c.data.max_instances = 8
    return c


def get_config(arg: str = "tiny") -> ml_collections.ConfigDict:
    """``"tiny"``, ``"cpu"``, ``"small"`` or ``"paper"`` (module docstring)."""
    c = _base()
    if arg == "tiny":
        c.total_steps = 1000
        c.batch_size = 16
        # One-to-many matching: with one positive patch per object a model this small, trained
        # from scratch, barely learns presence in 1000 steps (held-out AP50 0.010 vs 0.054
        # with 4, docs/training.md).
        c.loss.matches_per_target = 4
        c.optim.warmup_steps = 30
        c.eval.every_steps = 100
        c.eval.num_images = 8
        c.eval.num_examples = 64
        c.eval.batch_size = 8
        c.checkpoint.every_steps = 100
        c.log_every = 20
    elif arg == "cpu":
        c.total_steps = 8000
        c.batch_size = 16
        c.model.variant = "mini/16"
        c.loss.matches_per_target = 4
        c.data.num_train_templates = 32
        c.optim.warmup_steps = 200
        c.eval.update(every_steps=1000, num_images=16, num_examples=128, batch_size=16)
        c.checkpoint.every_steps = 1000
        c.log_every = 100
    elif arg == "small":
        c.total_steps = 20_000
        c.batch_size = 64
        c.model.update(variant="S/16", image_size=512, render_size=112, remat=False)
        c.data.update(max_instances=16, num_train_templates=64, num_workers=8)
        c.optim.update(learning_rate=4e-4, warmup_steps=1000)
        c.eval.update(every_steps=2000, num_images=128, num_examples=1024, batch_size=64, template_chunk=512)
        c.checkpoint.every_steps = 1000
        c.log_every = 100
    elif arg == "paper":
        c.total_steps = 250_000
        c.batch_size = 4096
        # On NVIDIA GPUs add --config.model.attention_impl=cudnn (flash attention, bf16).
        c.model.update(variant="B/16", image_size=512, render_size=224, remat=True)
        c.data.update(max_instances=32, num_train_templates=128, max_symmetries=128,
                      num_workers=16, worker_buffer_size=4)
        c.optim.update(learning_rate=3e-4, warmup_steps=10_000, weight_decay=0.05)
        c.eval.update(every_steps=10_000, num_images=1024, num_examples=8192, batch_size=512,
                      template_chunk=1024)
        c.checkpoint.update(every_steps=2000, max_to_keep=3)
        c.mesh.update(data=-1, fsdp=8)
        c.log_every = 100
    else:
        raise ValueError(f"unknown detector config {arg!r}; use tiny, cpu, small or paper "
                         "(train/configs/detector.py:tiny)")
    return c
