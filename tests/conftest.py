"""Test configuration: CPU only, four fake devices for sharding tests, shared BOP meshes."""

import os
import pathlib

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_num_cpu_devices", 4)

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHARED_MESHES = ROOT.parent / "shared" / "meshes" / "bop"


@pytest.fixture(scope="session")
def bop_models_dir():
    """Directory holding the shared BOP model folders (``<dataset>/models``)."""
    if not SHARED_MESHES.is_dir():
        pytest.skip(f"shared BOP meshes not found at {SHARED_MESHES} (CI has them beside the checkout)")
    return SHARED_MESHES
