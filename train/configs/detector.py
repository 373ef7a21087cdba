"""3PT-D training configs: ``get_config("tiny" | "small" | "paper")``.

Used as ``python train/launch.py --config train/configs/detector.py:tiny --workdir DIR
[--config.key=value ...]``. Every config has top-level ``total_steps``, ``batch_size`` (global,
over all processes and devices) and ``data_dir`` (a records folder with ``train/`` and ``val/``
ArrayRecord shards, ``objects.json`` and ``banks/``, written by ``python -m datagen.pack``).

* ``tiny``: CPU, tests and the demo: 128 px tiles, the "tiny/16" ViT (width 64, depth 2),
  32 px renders, 16 templates per example, batch 16, 1000 steps (about 4 minutes on 2 cores),
  one-to-many matching (4 positives per object).
* ``small``: one GPU in under an hour: S/16 on 512 px tiles, 112 px renders, batch 64,
  64 templates per example, 20k steps.
* ``paper``: the paper's sizes and data scale (DESIGN.md section 1.1): B/16 on 512 px tiles,
  224 px renders, the 5140-template bank (128 sampled per example in a step, the whole bank
  at evaluation), global batch 4096 over many hosts with FSDP, 250k steps (~1B image-render
  pairs: 4096 tiles x 250k steps, each with 12 prior + 128 template renders).
"""

from __future__ import annotations

import ml_collections


def _base() -> ml_collections.ConfigDict:
    c = ml_collections.ConfigDict()
    c.trainer = "detector"  # which train/trainer_<name>.py launch.py runs
    c.seed = 0
    c.total_steps = 1000
    c.batch_size = 8
    c.data_dir = ""
    # "auto": jax.distributed.initialize() when launched on several hosts (detected from the
    # cluster's environment); True/False force it.
    c.distributed = "auto"

    c.model = ml_collections.ConfigDict(dict(
        variant="tiny/16",
        image_size=128,  # the tile side, also the data pipeline's tile
        render_size=32,
        tokens_per_view=4,
        embed_dim=ml_collections.FieldReference(None, field_type=int),
        num_registers=0,
        posemb="learned",
        share_backbone=True,
        attention_impl=ml_collections.FieldReference(None, field_type=str),
        remat=False,
        dtype="auto",  # bfloat16 on accelerators, float32 on CPU
        param_dtype="float32",
    ))
    c.loss = ml_collections.ConfigDict(dict(
        cost_class=2.0, cost_l1=5.0, cost_giou=2.0,
        presence_weight=2.0, l1_weight=5.0, giou_weight=2.0, orientation_weight=1.0,
        focal_alpha=0.25, focal_gamma=2.0, orientation_alpha=0.25, orientation_gamma=2.0,
        soft_matching=1.0,
        matches_per_target=1,
    ))
    c.optim = ml_collections.ConfigDict(dict(
        learning_rate=1e-3,
        warmup_steps=50,
        end_lr_factor=0.01,  # cosine decays to learning_rate * end_lr_factor
        b1=0.9, b2=0.999, eps=1e-8,
        weight_decay=0.05,  # on matrices only (ndim >= 2), not biases, norms or scalars
        grad_clip_norm=1.0,
    ))
    c.data = ml_collections.ConfigDict(dict(
        max_instances=8,
        num_train_templates=16,
        max_symmetries=64,
        negative_prob=0.2,
        scale_prior=(128.0, 350.0),
        min_query_visib=0.1,
        min_target_visib=0.1,
        min_box_size=2.0,
        num_train_records=-1,  # -1: every record of the split
        num_workers=0,  # grain multiprocess prefetch workers per process (0: in-process)
        worker_buffer_size=2,
        read_threads=4,
        prefetch_buffer_size=16,
        photometric=ml_collections.ConfigDict(dict(
            brightness=0.15, contrast=0.3, saturation=0.3, hue=0.03, noise_std=0.03,
            blur_prob=0.2, blur_sigma=1.2)),
    ))
    c.eval = ml_collections.ConfigDict(dict(
        every_steps=500,  # 0: no periodic evaluation
        num_examples=256,  # tiles from the val split (each queried with one object)
        batch_size=16,
        num_templates=-1,  # templates of the bank used for orientation (-1: all)
        template_chunk=256,  # templates embedded per chunk when building the banks
        max_detections=20,
        nms_iou=0.5,
        orientation_threshold_deg=15.0,
        match_iou=0.5,
        seed=1,
    ))
    c.checkpoint = ml_collections.ConfigDict(dict(
        every_steps=500,
        max_to_keep=3,
        best_metric="eval/ap50",
        best_mode="max",
        async_save=True,
    ))
    # Device mesh ("data", "fsdp"); -1 = all remaining devices. Parameters (and optimizer
    # moments) are sharded over "fsdp" on their largest divisible axis when they have at least
    # fsdp_min_size elements; the batch is sharded over both axes.
    c.mesh = ml_collections.ConfigDict(dict(data=-1, fsdp=1, fsdp_min_size=2**14))
    c.log_every = 50
    c.progress_bar = True
    return c


def get_config(arg: str = "tiny") -> ml_collections.ConfigDict:
    """``"tiny"``, ``"small"`` or ``"paper"`` (module docstring)."""
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
        c.eval.num_examples = 64
        c.eval.batch_size = 8
        c.checkpoint.every_steps = 100
        c.log_every = 20
    elif arg == "small":
        c.total_steps = 20_000
        c.batch_size = 64
        c.model.update(variant="S/16", image_size=512, render_size=112, remat=False)
        c.data.update(max_instances=16, num_train_templates=64, num_workers=8)
        c.optim.update(learning_rate=4e-4, warmup_steps=1000)
        c.eval.update(every_steps=2000, num_examples=1024, batch_size=64, template_chunk=512)
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
        c.eval.update(every_steps=10_000, num_examples=8192, batch_size=512,
                      template_chunk=1024)
        c.checkpoint.update(every_steps=2000, max_to_keep=3)
        c.mesh.update(data=-1, fsdp=8)
        c.log_every = 100
    else:
        raise ValueError(f"unknown detector config {arg!r}; use tiny, small or paper "
                         "(train/configs/detector.py:tiny)")
    return c
