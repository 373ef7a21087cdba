"""Training logs stay readable in a file: no progress bar off a terminal, step lines that name
the step of the total, averages of the steps since the last line."""

import os

from train.logging_utils import MetricLogger
from train.stages import log_friendly_progress


def test_off_a_terminal_the_step_lines_are_the_progress(tmp_path, capsys):
    log = MetricLogger(tmp_path, total_steps=10, start_step=0, examples_per_step=4)
    assert log.bar is None  # pytest captures stderr: not a terminal
    for loss in (1.0, 3.0):
        log.update({"loss": loss})
    means = log.flush(2)
    log.close()
    assert means["loss"] == 2.0
    out = capsys.readouterr()
    assert out.out.startswith("step 2/10: ") and "loss=2" in out.out
    assert "\r" not in out.out + out.err


def test_log_friendly_progress_slows_tqdm_off_a_terminal(monkeypatch):
    monkeypatch.setenv("TQDM_MININTERVAL", "0")  # recorded, so the test leaves it as it was
    monkeypatch.delenv("TQDM_MININTERVAL")
    log_friendly_progress()
    assert os.environ["TQDM_MININTERVAL"] == "30"
