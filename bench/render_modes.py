"""Dr.Jit's wavefront mode against its symbolic mode for data generation, from an empty kernel
cache (docs/datagen.md, "Rendering speed").

Each arm generates the same scenes (``datagen.generate``, the learning test's settings by
default) in a fresh process whose Dr.Jit kernel cache (``DRJIT_CACHE_DIR``) is a new empty
folder, then again with that cache filled but new scenes (another seed): what a fresh machine
and a warm one pay. The symbolic arm replaces ``mitsuba_backend._wavefront`` by a null context.
Prints seconds per arm and the ratio wavefront / symbolic.

    python bench/render_modes.py [--scenes 10] [--images-per-scene 4]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

CHILD = """
import contextlib, sys
from threept_jax.render import mitsuba_backend
if sys.argv[1] == "symbolic":
    mitsuba_backend._wavefront = lambda lanes: contextlib.nullcontext()
from datagen import generate
generate.main(sys.argv[2:])
"""


def run(mode: str, cache: str, out: str, seed: int, args) -> float:
    argv = ["--meshes", "procedural:24", "--resolution", "160", "128", "--spp", "2",
            "--max-depth", "3", "--instances", "8", "--distinct", "2", "6", "--quiet",
            "--num-scenes", str(args.scenes), "--images-per-scene", str(args.images_per_scene),
            "--seed", str(seed), "--out", out]
    t = time.perf_counter()
    subprocess.run([sys.executable, "-c", CHILD, mode, *argv], check=True,
                   env={**os.environ, "DRJIT_CACHE_DIR": cache})
    return time.perf_counter() - t


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", type=int, default=10)
    p.add_argument("--images-per-scene", type=int, default=4)
    args = p.parse_args()
    times = {}
    for mode in ("symbolic", "wavefront"):
        with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as out:
            cold = run(mode, cache, out + "/a", 0, args)
            warm = run(mode, cache, out + "/b", 1, args)
        times[mode] = (cold, warm)
        print(f"{mode:9s}: empty cache {cold:6.1f} s, filled cache and new scenes {warm:6.1f} s",
              flush=True)
    for i, name in enumerate(("empty cache", "filled cache")):
        print(f"wavefront / symbolic, {name}: {times['wavefront'][i] / times['symbolic'][i]:.2f}")


if __name__ == "__main__":
    main()
