"""Compile time of a training run's jitted initialisation (issue 39), with and without
``train.trainer.FAST_COMPILE_OPTIONS``, and of a fine-tuning run's start.

For the detector and the refiner of a training config (``tiny`` by default), the trainer's
``init_state`` (every parameter drawn, the optimizer state made) is jitted twice in fresh
functions: with XLA's default options (the reference, same process) and with the fast-compile
options the trainer uses. A run with ``init_from`` draws nothing: it starts from the loaded
parameters with ``fresh_state`` (the optimizer state alone), timed the same way on the drawn
parameters. Printed per model: cold seconds (lowering and compilation) and warm seconds of one
run of each, and the ratios of the compile times. Run it alone: the figures are wall time on
this machine's cores.

    python bench/compile_init.py [--config tiny]
"""

from __future__ import annotations

import argparse
import functools
import time

import jax
from flax import nnx

from threept_jax.models.detector import Detector
from threept_jax.models.refiner import Refiner
from train import run_config
from train.configs import detector as detector_configs
from train.configs import refiner as refiner_configs
from train.trainer import FAST_COMPILE_OPTIONS, fresh_state, init_state, make_optimizer


def measure(fn, *args) -> tuple[float, float, dict]:
    """(cold s, warm s, the output) of the jitted ``fn`` on ``args``: lowering and compiling,
    then one run."""
    start = time.perf_counter()
    compiled = fn.lower(*args).compile()
    cold = time.perf_counter() - start
    start = time.perf_counter()
    out = jax.block_until_ready(compiled(*args))
    return cold, time.perf_counter() - start, out


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

        tx, _ = make_optimizer(config.optim.to_dict(), int(config.total_steps))
        init = functools.partial(init_state, make_model, tx)
        ref_cold, ref_warm, _ = measure(jax.jit(init))
        fast_cold, fast_warm, state = measure(
            jax.jit(init, compiler_options=FAST_COMPILE_OPTIONS))
        start_cold, start_warm, _ = measure(
            jax.jit(functools.partial(fresh_state, tx=tx), compiler_options=FAST_COMPILE_OPTIONS),
            state["params"])
        print(f"{name:9s} default: compile {ref_cold:5.1f} s, run {ref_warm:.3f} s | "
              f"fast-compile: compile {fast_cold:5.1f} s, run {fast_warm:.3f} s | "
              f"compile ratio {fast_cold / ref_cold:.2f} | init_from start: compile "
              f"{start_cold:5.2f} s, run {start_warm:.3f} s, ratio to the fast init "
              f"{start_cold / fast_cold:.2f}")


if __name__ == "__main__":
    main()
