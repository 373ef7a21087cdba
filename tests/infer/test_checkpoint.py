"""``infer.checkpoint``: a refiner whose own held-out evaluation says it makes poses worse is
loaded with a warning that says so."""

import warnings

import pytest

from infer.checkpoint import RefinerWarning, heldout_check, load_refiner
from tests.fixtures.run_dirs import tiny_refiner_run
from threept_jax.data.run_dir import RunDir


def test_heldout_check_by_hand():
    assert heldout_check({}) is None  # no held-out metrics saved: nothing to say
    assert heldout_check({"eval/ar_mssd_before": 0.49, "eval/ar_mssd_after": 0.49}) is None
    assert heldout_check({"eval/ar_mssd_before": 0.30, "eval/ar_mssd_after": 0.52}) is None
    text = heldout_check({"eval/ar_mssd_before": 0.490, "eval/ar_mssd_after": 0.302})
    assert "makes poses worse" in text and "0.490" in text and "0.302" in text


def test_load_refiner_warns_from_the_checkpoints_metrics(tmp_path, monkeypatch):
    run = tiny_refiner_run(tmp_path / "r")
    with warnings.catch_warnings():
        warnings.simplefilter("error", RefinerWarning)
        load_refiner(run)  # the fixture saves no metrics
    monkeypatch.setattr(RunDir, "saved_metrics", lambda self, step: {
        "eval/ar_mssd_before": 0.49, "eval/ar_mssd_after": 0.30})
    with pytest.warns(RefinerWarning, match=r"step 0: .*makes poses worse"):
        load_refiner(run)
