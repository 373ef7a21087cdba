"""Compile time of a training run's jitted initialisation (issue 39), with and without
``train.trainer.FAST_COMPILE_OPTIONS``.

For the detector and the refiner of a training config (``tiny`` by default), the trainer's
``init_state`` (every parameter drawn, the optimizer state made) is jitted twice in fresh
functions: with XLA's default options (the reference, same process) and with the fast-compile
options the trainer uses. Printed per model: cold seconds (lowering and compilation) and warm
seconds of one run of each, and the ratio of the compile times. Run it alone: the figures are
wall time on this machine's cores.

    python bench/compile_init.py [--config tiny]
"""

from __future__ import annotations

import argparse
import time

import jax
from flax import nnx

from threept_jax.models.detector import Detector
from threept_jax.models.refiner import Refiner
from train import run_config
from train.configs import detector as detector_configs
from train.configs import refiner as refiner_configs
from train.trainer import FAST_COMPILE_OPTIONS, init_state, make_optimizer


def measure(make_model, config, options) -> tuple[float, float]:
    """(cold s, warm s) of the jitted ``init_state`` compiled with ``options``."""
    tx, _ = make_optimizer(config.optim.to_dict(), int(config.total_steps))
    init = jax.jit(lambda: init_state(make_model, tx), compiler_options=options)
    start = time.perf_counter()
    compiled = init.lower().compile()
    cold = time.perf_counter() - start
    start = time.perf_counter()
    jax.block_until_ready(compiled())
    return cold, time.perf_counter() - start


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", default="tiny", help="training config of both models")
    args = p.parse_args()
    models = {
        "detector": (detector_configs.get_config(args.config), Detector),
        "refiner": (refiner_configs.get_config(args.config), Refiner),
    }
    print(f"{jax.devices()[0].device_kind}, {args.config} configs; init_state jitted")
    for name, (config, cls) in models.items():
        cfg = run_config.model_config(config)

        def make_model(cfg=cfg, cls=cls):
            return cls(cfg, rngs=nnx.Rngs(0))

        ref_cold, ref_warm = measure(make_model, config, None)
        fast_cold, fast_warm = measure(make_model, config, FAST_COMPILE_OPTIONS)
        print(f"{name:9s} default: compile {ref_cold:5.1f} s, run {ref_warm:.3f} s | "
              f"fast-compile: compile {fast_cold:5.1f} s, run {fast_warm:.3f} s | "
              f"compile ratio {fast_cold / ref_cold:.2f}")


if __name__ == "__main__":
    main()
