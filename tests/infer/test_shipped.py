"""The shipped models (``infer.shipped``): an exported run loads by default, and a missing,
damaged or foreign file is refused naming the file and ``git checkout``."""

import json
import pathlib
import shutil
import subprocess

import cv2
import jax
import numpy as np
import pytest
from flax import nnx

import infer
from infer import shipped
from infer.checkpoint import load_detector
from tests.fixtures.cli import fails_naming
from tests.fixtures.run_dirs import tiny_detector_run
from threept_jax.data.run_dir import ModelFileError
from threept_jax.pipeline.contour import ContourSettings
from train import export


@pytest.fixture
def models_dir(tmp_path, monkeypatch) -> pathlib.Path:
    """A models/ folder holding an exported untrained detector as the shipped one."""
    run = tiny_detector_run(tmp_path / "run")
    models = tmp_path / "repo" / "models"
    info = export.export(run, models / "detector-cpu")
    assert info == {"best": 0, "latest": 0, "resumable": False, "megabytes": info["megabytes"]}
    (models / shipped.SHIPPED_FILE).write_text('{"detector": "detector-cpu", "refiner": null}')
    monkeypatch.setattr(shipped, "MODELS_DIR", models)
    return models


def _params(model) -> list[np.ndarray]:
    return [np.asarray(x) for x in jax.tree.leaves(nnx.state(model, nnx.Param))]


def test_exported_model_matches_sha256sum_and_loads_by_default(models_dir, tmp_path):
    folder = models_dir / "detector-cpu"
    # The checksums are in sha256sum's format: coreutils checks them independently.
    check = subprocess.run(["sha256sum", "--check", "--strict", "SHA256SUMS"], cwd=folder,
                           capture_output=True, text=True)
    assert check.returncode == 0, check.stdout + check.stderr
    assert not list(folder.rglob("opt_state")) and not list(folder.rglob("data"))
    # By default no network detects: the training-free templates detector, which measures
    # better on held-out cells; detector="3pt" loads the shipped 3PT-D.
    default = infer.load(cache_dir=None)
    assert default.detector is None and default.shape_search is not None
    models = infer.load(cache_dir=None, detector="3pt")
    # No 3PT-R ships: the training-free contour refiner is the default.
    assert isinstance(models.refiner, ContourSettings)
    assert isinstance(default.refiner, ContourSettings)
    original, _, _ = load_detector(tmp_path / "run")
    for a, b in zip(_params(models.detector), _params(original), strict=True):
        np.testing.assert_array_equal(a, b)
    # Loading writes nothing into the model: it still verifies.
    shipped.shipped("detector")


def test_damaged_missing_or_foreign_files_name_the_file_and_git_checkout(models_dir):
    folder = models_dir / "detector-cpu"
    restore = "git checkout -- models/detector-cpu"
    biggest = max((p for p in folder.rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)
    data = bytearray(biggest.read_bytes())
    data[len(data) // 2] ^= 0xFF
    biggest.write_bytes(bytes(data))
    with pytest.raises(ModelFileError, match="differs from its SHA-256") as e:
        infer.load(cache_dir=None, detector="3pt")
    assert str(biggest) in str(e.value) and restore in str(e.value)
    data[len(data) // 2] ^= 0xFF
    biggest.write_bytes(bytes(data))
    infer.load(cache_dir=None, detector="3pt")

    stray = folder / "checkpoints" / "stray.bin"
    stray.write_bytes(b"x")
    with pytest.raises(ModelFileError, match="is not part of the model") as e:
        shipped.shipped("detector")
    assert str(stray) in str(e.value)
    stray.unlink()

    (folder / "detector.json").unlink()
    with pytest.raises(ModelFileError, match="the shipped detector is missing") as e:
        infer.load(cache_dir=None, detector="3pt")
    assert str(folder / "detector.json") in str(e.value) and restore in str(e.value)
    shutil.rmtree(folder)
    with pytest.raises(ModelFileError, match=restore):
        infer.load(cache_dir=None, detector="3pt")


def test_cli_without_workdir_uses_the_shipped_detector_and_reports_damage(models_dir, tmp_path,
                                                                         capsys, bop_models_dir):
    ply = next(bop_models_dir.rglob("*.ply"))
    image = tmp_path / "a.png"
    cv2.imwrite(str(image), np.zeros((48, 64, 3), np.uint8))
    argv = ["images", "--detector", "3pt", "--mesh", f"1={ply}", "--image", str(image), "--K",
            "60,60,31.5,23.5",
            "--out", str(tmp_path / "out"), "--cache-dir", str(tmp_path / "cache")]
    (models_dir / "detector-cpu" / "config.json").write_text("{}")
    fails_naming(capsys, argv, "config.json differs from its SHA-256")


def test_the_committed_detector_is_whole_and_loads():
    """The repository's own shipped detector: every file matches its SHA256SUMS, its parameters
    restore into the network its config builds (a renamed or reshaped parameter fails here)
    and were trained (they differ from the network's initial values), and it carries the
    campaign plan it was trained under."""
    folder = shipped.shipped("detector")
    check = subprocess.run(["sha256sum", "--check", "--strict", "SHA256SUMS"], cwd=folder,
                           capture_output=True, text=True)
    assert check.returncode == 0, check.stdout + check.stderr
    model, cfg, step = load_detector(folder)
    assert step > 0
    from threept_jax.models.detector import Detector

    init = Detector(cfg, rngs=nnx.Rngs(0))
    assert any(not np.array_equal(a, b) for a, b in zip(_params(model), _params(init),
                                                        strict=True))
    plan = json.loads((folder / "campaign.json").read_text())
    assert plan["detector"]["config"] == "cpu" and plan["data"]["parts"] > 0
