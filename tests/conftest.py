"""Test configuration: CPU only, four fake devices for sharding tests, shared BOP meshes."""

import os
import pathlib

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import pytest  # noqa: E402
from fixtures.training import STEPS  # noqa: E402
from jax._src.interpreters import pxla as _pxla  # noqa: E402

from train.trainer import FAST_COMPILE_OPTIONS  # noqa: E402

jax.config.update("jax_num_cpu_devices", 4)

# Most of the suite's time is XLA compiling programs that then run a few times (docs/testing.md).
# So every module compiles with FAST_COMPILE_OPTIONS (no LLVM optimisation, XLA:CPU's loop
# emitters), its eager ``jnp`` operations and random initialisations too, but for the programs
# of OPTIMISED (and of RUN_MANY in the modules of FAST_BUT), and for the modules of
# OPTIMISED_MODULES, which compile everything at XLA's default level. Each module was measured alone both ways on 2
# cores; the figures are in docs/testing.md (2026-11-30, seventh session, and the sessions
# before).
#: Modules that compile every program optimised: the rasterizer's tests compare programs of one
#: renderer to float32 rounding (its leading-dimension test fails by 3e-6 relative when its
#: vmapped program is unoptimised).
OPTIMISED_MODULES = ("tests/render/test_raster.py",)
#: Programs that every module but OPTIMISED_MODULES still compiles optimised (with their own
#: options: the rasterizer's loop emitters, ``raster.RASTER_COMPILE_OPTIONS``): they run far more
#: than they compile. The rasterizer renders onboarding banks and contour models (1000 views a
#: mesh): unoptimised, a contour model took 5.3 s a mesh against 2.0 s (warm, 2 cores).
OPTIMISED = ("jit__render_impl",)
#: Modules that compile every program fast but those of RUN_MANY, which they run hundreds of
#: times: the learning tests' train steps (100 and 400 steps) and the noise ladder's loop (10
#: ladders; the module alone 177 -> 152 s against compiling everything optimised). Their
#: evaluations, initialisations and eager operations run once or twice (test_refiner_learning's
#: evaluation took 19 s to compile optimised). One rule for the four (each has only its own of
#: RUN_MANY's programs), so that a worker running two of them in a row keeps its caches.
FAST_BUT = ("tests/pipeline/test_refine_ladder.py", "tests/train/test_refiner_learning.py",
            "tests/train/test_learning.py", "tests/train/test_cell_detector.py")
RUN_MANY = ("jit__refine", "jit_train_step", "jit_step")
#: The programs the running module compiles optimised; None: all of them (OPTIMISED_MODULES).
_optimised: list[tuple[str, ...] | None] = [None]
_create_compile_options = _pxla.create_compile_options


def _compile_options(computation, *args):
    """``pxla.create_compile_options`` (jax 0.10) with FAST_COMPILE_OPTIONS under the options
    a program asked for, unless the running module compiles that program optimised."""
    *args, compiler_options = args
    name = str(computation.operation.attributes["sym_name"]).strip('"')
    if _optimised[0] is not None and name not in _optimised[0]:
        compiler_options = {**FAST_COMPILE_OPTIONS, **compiler_options}
    return _create_compile_options(computation, *args, compiler_options)


_pxla.create_compile_options = _compile_options
# The commands under test turn on JAX's persistent compilation cache (``options.load_models``)
# for the whole worker process, pointing into a test's temporary folder: a later test of the
# same worker then wrote compiled programs there, and jax 0.10 crashed with a segmentation
# fault in ``compilation_cache.put_executable_and_time`` (seen in ``test_refiner_learning``
# after a command's test on the same worker). Tests never use the persistent cache.
jax.config.update("jax_enable_compilation_cache", False)

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHARED_MESHES = ROOT.parent / "shared" / "meshes" / "bop"


@pytest.fixture(scope="session")
def bop_models_dir():
    """Directory holding the shared BOP model folders (``<dataset>/models``)."""
    if not SHARED_MESHES.is_dir():
        pytest.skip(f"shared BOP meshes not found at {SHARED_MESHES} (CI has them beside the checkout)")
    return SHARED_MESHES


#: Modules whose tests take minutes (compilations, training runs), marked ``slow`` (``pytest -m
#: "not slow"`` is the quick loop) and scheduled first (``make test`` passes
#: ``--no-loadscope-reorder``: xdist's default sends modules with the most tests first, which
#: put these last and left one worker idle at the end), so that the
#: two xdist workers run them side by side while the many short tests fill the gaps at the end
#: (``make test`` groups each module on one worker, ``--dist loadscope``, so a module's compiled
#: fixtures are built once).
SLOW_FIRST = (  # by their measured test time, longest first (docs/testing.md), those of
    # those of one compile rule in a row where the order allows, so that each worker reuses
    # their compiled programs (``_optimisation_level``)
    "tests/train/test_adapt.py", "tests/pipeline/test_refine_loop.py",
    "tests/train/test_refiner_trainer.py", "tests/train/test_detector_trainer.py",
    "tests/train/test_cluster.py", "tests/infer/test_track_cli.py",
    "tests/infer/test_refine_api.py", "tests/infer/test_bop_runner.py",
    "tests/train/test_resume.py", "tests/scripts/test_device.py",
    "tests/pipeline/test_refine_ladder.py", "tests/train/test_refiner_learning.py",
    "tests/train/test_learning.py", "tests/train/test_cell_detector.py",
    "tests/train/test_campaign.py",
    "tests/infer/test_shipped_guard.py", "tests/pipeline/test_refinement.py",
    "tests/pipeline/test_contour.py", "tests/pipeline/test_shape_search.py",
    "tests/datagen/test_mesh_kinds.py",
)


def _module_path(item) -> str:
    return pathlib.Path(str(item.fspath)).resolve().relative_to(ROOT).as_posix()


#: The compile rule of the programs in this worker's caches (``_module_rule``); [] none yet.
_cached_rule: list = []


def _module_rule(module: str) -> tuple[str, ...] | None:
    """The programs ``module`` compiles optimised: None for all of them (XLA's default level)."""
    if module in OPTIMISED_MODULES:
        return None
    return OPTIMISED + (RUN_MANY if module in FAST_BUT else ())


@pytest.fixture(scope="module", autouse=True)
def _optimisation_level(request):
    """Programs compiled by a module (its module fixtures included: an autouse fixture comes
    first in its scope) skip LLVM's optimisations, but those the module's rule names
    (``_module_rule``).

    A module whose rule is not that of the programs the worker holds starts with JAX's
    in-memory caches and the shared training steps emptied, so no program compiled at one
    level runs at the other: the levels round floats differently (eager ``jnp`` ops too), and
    a later module comparing its results with a subprocess's got other bits
    (``datagen.generate``'s one-thread test failed that way in CI). Modules of one level in a
    row share their programs (the training steps of ``small_config`` in ``fixtures.training.STEPS``,
    the tiny detector's full-image functions).
    """
    rule = _module_rule(_module_path(request.node))
    if _cached_rule and _cached_rule[0] != rule:
        _forget_compiled_programs()
    _cached_rule[:] = [rule]
    _optimised[0] = rule
    yield
    _optimised[0] = None


def _forget_compiled_programs():
    jax.clear_caches()
    STEPS.clear()


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(SLOW_FIRST)}

    def key(item):
        return rank.get(_module_path(item), len(SLOW_FIRST))

    for item in items:
        if key(item) < len(SLOW_FIRST):
            item.add_marker(pytest.mark.slow)
    items.sort(key=key)  # stable: the order within a module and among the rest is kept
