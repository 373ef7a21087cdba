"""Log every XLA compilation of a Python process, for docs/testing.md ("Where the minutes go").

Put this folder first on ``PYTHONPATH`` and name an output folder in ``THREEPT_COMPILE_LOG``;
every process then appends one line per compilation to ``<folder>/<pid>.tsv``: the time, the
seconds XLA took, a hash of the program's text, a hash of its compile-option overrides (the
tests' ``FAST_COMPILE`` level), the program's name and the test that ran it
(``PYTEST_CURRENT_TEST``)::

    THREEPT_COMPILE_LOG=/tmp/complog PYTHONPATH=scripts/compile_log \\
        .venv/bin/python -m pytest -n 2 --dist loadscope --no-loadscope-reorder -q tests
    .venv/bin/python scripts/compile_log/summary.py /tmp/complog

Programs found in JAX's in-memory caches are not compiled and not logged. The training tests'
subprocesses (``tests/fixtures/training.py`` ``SUBPROCESS_ENV``) put this folder on their
``PYTHONPATH`` too when ``THREEPT_COMPILE_LOG`` is set, and are logged with the test ``-``.
It wraps ``jax._src.compiler.backend_compile_and_load`` (jax 0.10), a private function: a JAX
that renames it turns the log off with a warning, never the process.
"""

import hashlib
import os
import time

_FOLDER = os.environ.get("THREEPT_COMPILE_LOG")


def _install(folder: str) -> None:
    from jax._src import compiler

    compile_and_load = compiler.backend_compile_and_load

    def logged(backend, module, executable_devices, options, host_callbacks):
        start = time.time()
        try:
            return compile_and_load(backend, module, executable_devices, options, host_callbacks)
        finally:
            seconds = time.time() - start
            text = module.operation.get_asm(large_elements_limit=16)
            overrides = str(getattr(options, "env_option_overrides", None))
            name = str(module.operation.attributes["sym_name"]).strip('"')
            test = os.environ.get("PYTEST_CURRENT_TEST", "-").split(" ")[0]
            with open(os.path.join(folder, f"{os.getpid()}.tsv"), "a") as f:
                f.write(f"{start:.1f}\t{seconds:.3f}\t"
                        f"{hashlib.sha1(text.encode()).hexdigest()[:12]}\t"
                        f"{hashlib.sha1(overrides.encode()).hexdigest()[:6]}\t{name}\t{test}\n")

    compiler.backend_compile_and_load = logged


if _FOLDER:
    try:
        os.makedirs(_FOLDER, exist_ok=True)
        _install(_FOLDER)
    except (ImportError, AttributeError) as e:  # another JAX: no log, never a broken process
        import warnings

        warnings.warn(f"THREEPT_COMPILE_LOG: cannot wrap JAX's compiler ({e}); nothing is logged",
                      stacklevel=1)
