"""scripts/compile_log: the compile hook logs a process's compilations; the summary's sums."""

import os
import subprocess
import sys

from fixtures.training import ROOT

LOG = ROOT / "scripts" / "compile_log"


def test_the_hook_logs_each_compilation_with_its_test(tmp_path):
    code = ("import jax, jax.numpy as jnp\n"
            "def doubled(x):\n    return 2 * x\n"
            "jax.jit(doubled)(jnp.arange(3.0))\njax.jit(doubled)(jnp.arange(3.0))\n"
            "jax.jit(doubled)(jnp.arange(4.0))\n")
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "THREEPT_COMPILE_LOG": str(tmp_path / "log"),
           "PYTHONPATH": str(LOG), "PYTEST_CURRENT_TEST": "tests/x.py::test_y (call)"}
    subprocess.run([sys.executable, "-c", code], env=env, check=True, timeout=120)
    (log,) = (tmp_path / "log").glob("*.tsv")
    rows = [line.split("\t") for line in log.read_text().splitlines()]
    mine = [r for r in rows if r[4] == "jit_doubled"]
    # Two shapes, two programs; the second call of the first shape hit JAX's in-memory cache.
    assert len(mine) == 2 and mine[0][2] != mine[1][2]
    assert all(r[5] == "tests/x.py::test_y" and float(r[1]) >= 0 for r in rows)


def test_summary_sums_by_program_and_counts_repeats_after_the_first(tmp_path):
    (tmp_path / "1.tsv").write_text("0\t2.0\taaa\to\tjit_a\tt/m.py::x\n"
                                    "0\t1.5\tbbb\to\tjit_b\tt/m.py::y\n")
    (tmp_path / "2.tsv").write_text("0\t3.0\taaa\to\tjit_a\tt/n.py::z\n"
                                    "0\t0.1\taaa\tp\tjit_a\tt/n.py::z\n")  # other options
    out = subprocess.run([sys.executable, str(LOG / "summary.py"), str(tmp_path)],
                         capture_output=True, text=True, check=True, timeout=60).stdout
    assert "6.6 s of XLA compilation in 4 compilations" in out
    assert "     5.1     3  jit_a" in out and "     3.1     2  t/n.py" in out
    # jit_a with options o ran twice: 3.0 s after the first; with p once (not a repeat).
    assert "repeated programs: 3.0 s" in out


def test_summary_refuses_a_file_that_is_not_a_compile_log(tmp_path):
    (tmp_path / "7.tsv").write_text("0\t2.0\tjit_a\n")
    proc = subprocess.run([sys.executable, str(LOG / "summary.py"), str(tmp_path)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1 and "7.tsv:1: not a line of" in proc.stderr
    assert "Traceback" not in proc.stderr
