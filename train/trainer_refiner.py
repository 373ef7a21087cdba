"""3PT-R trainer: the refiner's data, its pure train step and its evaluator.

``train(config, workdir)`` (what ``train/launch.py`` runs for ``config.trainer = "refiner"``,
``train/configs/refiner.py``) builds a :class:`RefinerTrainer` and runs it to
``config.total_steps``; the run itself (state, optimizer, checkpoints with the data
iterator, resume, preemption, finiteness checks, TensorBoard, progress bar) is
:class:`train.trainer.Trainer`, the detector's machinery.

* **Input** (:mod:`threept_jax.data.refiner_input`): the packed ArrayRecords of
  ``config.data_dir`` (``datagen.pack`` writes them with the meshes), one instance of
  visibility >= ``data.min_visib`` per example with ``data.num_hypotheses`` perturbed poses
  (that module states the noise), cropped around the first one. The meshes of
  ``objects.json`` are prepared (decimated to ``refine.max_faces``) and padded to one face
  budget (:class:`~threept_jax.data.refiner_input.RefinerMeshes`), so one compiled step
  serves every object; they enter the jitted step as an argument placed once on the devices.
* **Step** (:func:`make_train_step`): renders, one forward pass, the three losses and the
  classification target of one refinement step (:mod:`train.refiner_objective`), inside
  ``jax.jit``, the batch sharded over the mesh, the state donated; AdamW as the detector.
* **Evaluation** (:mod:`train.eval_refiner`) on objects training never saw
  (``eval.data_dir``): matching accuracy, pose error before and after 1 and
  ``eval.num_steps`` refinement steps, score accuracy, mask IoU; ``eval/ar_mssd_after``
  ranks the checkpoints by default.
"""

from __future__ import annotations

import json
from collections.abc import Iterable

import grain
import jax
import ml_collections
import optax
from flax import nnx

from threept_jax.data.pretrained import stem_params
from threept_jax.data.refiner_input import RefinerMeshes, refiner_dataset
from threept_jax.losses.refiner import RefinerLossConfig
from threept_jax.models.configs import RefinerConfig
from threept_jax.models.refiner import Refiner
from threept_jax.pipeline.refinement import RefineSettings
from train.eval_refiner import RefinerEvaluator
from train.refiner_objective import STEP_FIELDS, RefinerAssets, objective, render_batch
from train.run_config import loss_config, model_config, refine_settings, refiner_example_config
from train.trainer import (
    CompiledStep,
    Hook,
    StepCache,
    Trainer,
    apply_gradients,
    compile_step,
    frozen_groups,
    hold_frozen,
    make_optimizer,
)


def make_train_step(graphdef: nnx.GraphDef, tx: optax.GradientTransformation,
                    schedule: optax.Schedule, model_cfg: RefinerConfig,
                    loss_cfg: RefinerLossConfig, settings: RefineSettings,
                    trace_counter: list[int] | None = None, frozen: frozenset[str] = frozenset()):
    """``train_step(state, batch, assets) -> (state, metrics)``, pure (module docstring).

    ``frozen``: parameter groups behind ``hold_frozen`` (``config.optim.freeze``): no
    backward pass through them (the optimizer leaves them unchanged either way).

    ``batch`` holds :data:`~train.refiner_objective.STEP_FIELDS` with a leading batch axis;
    ``assets`` is the :class:`~train.refiner_objective.RefinerAssets` of the run's objects.
    ``trace_counter[0]`` counts the traces (tests check that it compiles once).
    """

    def loss_fn(params, batch, assets):
        model = nnx.merge(graphdef, hold_frozen(params, frozen))
        rend = render_batch(assets, batch, crop_size=model_cfg.crop_size,
                            output_size=model_cfg.output_size, ambient=settings.ambient)
        outputs = model(batch["crops"], rend.rgb)
        loss, metrics, _ = objective(outputs, rend, assets, batch, loss_cfg, settings)
        return loss, metrics

    def train_step(state, batch, assets):
        if trace_counter is not None:
            trace_counter[0] += 1
        (_, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            state["params"], batch, assets)
        return apply_gradients(state, grads, metrics, tx, schedule)

    return train_step


def build_step(config: ml_collections.ConfigDict, assets: RefinerAssets,
               mesh: jax.sharding.Mesh) -> CompiledStep:
    """Model graph, abstract state, shardings, jitted init and the jitted step of ``config``
    with ``assets`` bound (compiled on its first call)."""
    model_cfg = model_config(config)
    tx, schedule = make_optimizer(config.optim.to_dict(), int(config.total_steps))
    make_model = lambda: Refiner(model_cfg, rngs=nnx.Rngs(int(config.seed)))  # noqa: E731
    graphdef = nnx.graphdef(nnx.eval_shape(make_model))
    counter = [0]
    step_fn = make_train_step(graphdef, tx, schedule, model_cfg, loss_config(config),
                              refine_settings(config), counter,
                              frozen=frozen_groups(config.optim.freeze))
    return compile_step(make_model, step_fn, tx, schedule, mesh,
                        int(config.mesh.fsdp_min_size), counter, assets=assets)


class RefinerTrainer(Trainer):
    """One 3PT-R run (module docstring; the run itself is :class:`train.trainer.Trainer`)."""

    step_fields = STEP_FIELDS
    data_hint = ("instances with visible masks and meshes in objects.json (iterate "
                 "threept_jax.data.refiner_input.refiner_dataset by hand)")

    def prepare_data(self) -> None:
        c = self.config
        self.meshes = RefinerMeshes.from_records(c.data_dir, max_faces=c.refine.max_faces)
        self.assets = RefinerAssets.from_meshes(self.meshes)

    def step_key(self):
        c = self.config
        sections = {k: c[k].to_dict() for k in ("model", "loss", "refine", "optim")}
        return ("refiner", json.dumps(sections, sort_keys=True, default=str),
                int(c.total_steps), int(c.seed), str(c.data_dir), self.mesh,
                int(c.mesh.fsdp_min_size))

    def build_step(self) -> CompiledStep:
        return build_step(self.config, self.assets, self.mesh)

    def train_dataset(self) -> grain.MapDataset:
        c = self.config
        return refiner_dataset(
            c.data_dir, "train", refiner_example_config(c), seed=c.seed,
            batch_size=self.local_batch, process_index=jax.process_index(),
            process_count=jax.process_count(),
            num_records=None if c.data.num_train_records < 0 else c.data.num_train_records)

    def make_evaluator(self) -> RefinerEvaluator:
        return RefinerEvaluator(self.config, self.compiled.graphdef, self.mesh)

    def pretrained_params(self, params):
        """A fresh run with ``model.pretrained_stem`` starts from the converted weights
        (``models/<stem>``, checked against their SHA256)."""
        stem = self.model_cfg.pretrained_stem
        if stem == "none":
            return params
        loaded = stem_params(stem)
        params = dict(params)
        params["stem"] = jax.tree.map(
            lambda old, new: jax.device_put(new.astype(old.dtype), old.sharding),
            params["stem"], loaded)
        return params


def train(config: ml_collections.ConfigDict, workdir, hooks: Iterable[Hook] = (),
          devices=None, step_cache: StepCache | None = None,
          allow_config_change: bool = False) -> dict:
    """Build a :class:`RefinerTrainer` from ``config`` (resuming from ``workdir``) and run it."""
    return RefinerTrainer(config, workdir, devices=devices, step_cache=step_cache,
                          allow_config_change=allow_config_change).run(hooks)
