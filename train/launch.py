"""Train a model: ``python train/launch.py --config train/configs/detector.py:tiny --workdir DIR``.

The config's ``trainer`` picks the trainer: ``train/configs/detector.py`` trains 3PT-D
(``train/trainer_detector.py``), ``train/configs/refiner.py`` trains 3PT-R
(``train/trainer_refiner.py``); both share one run machinery (``train/trainer.py``).

Overrides use ml_collections' syntax, e.g. ``--config.data_dir=/data/records
--config.total_steps=2000 --config.mesh.fsdp=4``; a key outside the config schema
(``train/run_config.py``) stops the launcher before anything runs, naming the valid keys. The
run resumes from the latest checkpoint in ``--workdir`` when there is one. On several hosts,
start the same command on every host (Slurm, Open MPI, or ``JAX_COORDINATOR_ADDRESS``,
``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID``): the launcher calls ``jax.distributed.initialize()``
first (``--config.distributed``; docs/cluster.md). SIGTERM saves a checkpoint
at the next step and exits 0. A resume refuses a config that changes the run's seed, batch
size, data or optimisation (``--allow_config_change`` allows it and keeps the old config in
``config_history.json``) and any change of the model.

Bad input (an unknown key, an out-of-range value, a batch the devices do not divide, missing
data, another run's workdir) stops the launcher with exit status 2 and one ``error:`` line.
"""

from __future__ import annotations

import re
import sys
from typing import NoReturn

from absl import app, flags, logging
from ml_collections import config_flags

_CONFIG = config_flags.DEFINE_config_file(
    "config", None, "Training config file and argument, e.g. train/configs/detector.py:tiny.",
    lock_config=True)
_WORKDIR = flags.DEFINE_string("workdir", None, "Run folder: checkpoints, TensorBoard logs.")
_ALLOW_CHANGE = flags.DEFINE_bool(
    "allow_config_change", False,
    "Resume even when the config changes keys the run's config.json fixes (seed, batch_size, "
    "data_dir, data/loss/optim settings, evaluation; train/run_config.py RESUME_FREE_KEYS "
    "lists the keys a resume may change without it). The old config is kept in "
    "config_history.json.")
flags.mark_flags_as_required(["config", "workdir"])

#: ``--config.a.b=v`` or ``--config.a.b v``: the override's key path.
_OVERRIDE = re.compile(r"^--?config\.([^=\s]+)")


def _fail(message: str) -> NoReturn:
    sys.stderr.write(f"error: {message}\n")
    sys.exit(2)


def _config_trainer(argv: list[str]) -> str:
    """The ``trainer`` of the config file named by ``--config`` (``"detector"`` if unreadable)."""
    import importlib.util

    for i, arg in enumerate(argv):
        if arg.startswith(("--config=", "-config=")):
            value = arg.split("=", 1)[1]
        elif arg in ("--config", "-config") and i + 1 < len(argv):
            value = argv[i + 1]
        else:
            continue
        path, _, name = value.partition(":")
        try:
            spec = importlib.util.spec_from_file_location("_run_config_file", path)
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
            return module.get_config(*([name] if name else [])).get("trainer", "detector")
        except Exception:  # the launcher's own parse reports a bad config file
            return "detector"
    return "detector"


def parse_flags(argv: list[str]) -> list[str]:
    """absl's flag parsing, with a one-line error for a config override naming no key.

    ml_collections reports an unknown override key as an AttributeError traceback; every key
    of the schema exists in the config (``default_config``), so a failing override is named
    here by checking each override's path against the config's trainer's schema.
    """
    from train import run_config

    try:
        return flags.FLAGS(argv)
    except flags.Error as e:
        _fail(f"{e}\nPass --helpfull to see the flags.")
    except (AttributeError, KeyError, TypeError) as e:
        trainer = _config_trainer(argv)
        for arg in argv[1:]:
            m = _OVERRIDE.match(arg)
            if m:
                try:
                    run_config.check_key(m.group(1), trainer)
                except run_config.ConfigError as bad:
                    _fail(f"{bad} (in {arg.split('=')[0]})")
        _fail(f"a --config override names a key the config file does not define: {e}")


def main(argv) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments {argv[1:]}")
    config = _CONFIG.value
    from train import run_config

    try:
        run_config.check_config(config)
    except run_config.ConfigError as e:
        _fail(f"{e} (in {flags.FLAGS['config'].config_filename})")
    if not flags.FLAGS["verbosity"].present:
        # Orbax logs every checkpoint step at INFO; our own progress goes to the console.
        logging.set_verbosity(logging.WARNING)
    from train import sharding

    # Before anything touches the devices.
    sharding.maybe_initialize_distributed(config.distributed)
    import jax

    from train.trainers import trainer_class

    print(f"process {jax.process_index()}/{jax.process_count()}, devices: {jax.devices()}",
          flush=True)
    try:
        trainer = trainer_class(config)(config, _WORKDIR.value,
                                        allow_config_change=_ALLOW_CHANGE.value)
    except (ValueError, FileNotFoundError, KeyError) as e:
        # Everything the trainer checks before it trains: the config against the devices, the
        # data and the workdir's run.
        _fail(e.args[0] if isinstance(e, KeyError) and e.args else str(e))
    summary = trainer.run()
    if summary["preempted"] is not None:
        print(f"stopped by SIGTERM after step {summary['preempted']} (checkpoint saved)",
              flush=True)
        return
    if jax.process_index() == 0 and summary.get("eval"):
        print("final eval: " + ", ".join(f"{k}={v:.4g}" for k, v in summary["eval"].items()))


if __name__ == "__main__":
    sys.exit(app.run(main, flags_parser=parse_flags))
