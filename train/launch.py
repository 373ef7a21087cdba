"""Train a model: ``python train/launch.py --config train/configs/detector.py:tiny --workdir DIR``.

Overrides use ml_collections' syntax, e.g. ``--config.data_dir=/data/records
--config.total_steps=2000 --config.mesh.fsdp=4``. The run resumes from the latest checkpoint
in ``--workdir`` when there is one. On several hosts, start the same command on every host
(SLURM, Open MPI or a coordinator address in ``JAX_COORDINATOR_ADDRESS``): the launcher calls
``jax.distributed.initialize()`` first (``--config.distributed``).
"""

from __future__ import annotations

import sys

from absl import app, flags, logging
from ml_collections import config_flags

_CONFIG = config_flags.DEFINE_config_file(
    "config", None, "Training config file and argument, e.g. train/configs/detector.py:tiny.",
    lock_config=True)
_WORKDIR = flags.DEFINE_string("workdir", None, "Run folder: checkpoints, TensorBoard logs.")
flags.mark_flags_as_required(["config", "workdir"])


def main(argv) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    config = _CONFIG.value
    if not flags.FLAGS["verbosity"].present:
        # Orbax logs every checkpoint step at INFO; our own progress goes to the console.
        logging.set_verbosity(logging.WARNING)
    from train import sharding

    # Before anything touches the devices.
    sharding.maybe_initialize_distributed(config.distributed)
    import jax

    if config.trainer != "detector":
        raise app.UsageError(f"unknown trainer {config.trainer!r} in the config (known: detector)")
    from train import trainer_detector

    print(f"process {jax.process_index()}/{jax.process_count()}, devices: {jax.devices()}",
          flush=True)
    summary = trainer_detector.train(config, _WORKDIR.value)
    if jax.process_index() == 0 and summary.get("eval"):
        print("final eval: " + ", ".join(f"{k}={v:.4g}" for k, v in summary["eval"].items()))


if __name__ == "__main__":
    sys.exit(app.run(main))
