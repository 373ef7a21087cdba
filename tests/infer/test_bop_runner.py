"""``python -m infer bop`` picks its objects before any slow work: only the run's targets are
onboarded, a target without a mesh is named (id and expected file); an image without
detections says so. Models are faked: these tests stop where the networks would start."""

import json

import cv2
import numpy as np
import pytest
import trimesh

from infer import bop_runner
from infer.cli import main
from infer.detect import Detections
from threept_jax.data import bop
from threept_jax.geometry.symmetry import Symmetries


class _Onboarding(Exception):
    """Raised by the fake models where onboarding would start."""


@pytest.fixture
def dataset(tmp_path):
    """models_info lists objects 1, 2, 3; only 1 and 2 have meshes; the BOP19 targets of the
    one test image are objects 1 and 2."""
    root = tmp_path / "ds"
    models = root / "models"
    models.mkdir(parents=True)
    info = {str(k): {"diameter": 100.0, "min_x": -10, "min_y": -10, "min_z": -10,
                     "size_x": 20, "size_y": 20, "size_z": 20} for k in (1, 2, 3)}
    (models / "models_info.json").write_text(json.dumps(info))
    for k in (1, 2):
        trimesh.creation.box((20, 20, 20)).export(models / f"obj_{k:06d}.ply")
    scene = root / "test" / "000001"
    (scene / "rgb").mkdir(parents=True)
    K = [60.0, 0, 31.5, 0, 60.0, 23.5, 0, 0, 1]
    (scene / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": K}}))
    cv2.imwrite(str(scene / "rgb" / "000000.png"), np.full((48, 64, 3), 90, np.uint8))
    (root / "test_targets_bop19.json").write_text(json.dumps(
        [{"scene_id": 1, "im_id": 0, "obj_id": k, "inst_count": 1} for k in (1, 2)]))
    (root / "test_targets_bop24.json").write_text(json.dumps([{"scene_id": 1, "im_id": 0}]))
    return root


def _argv(root, *extra):
    return ["bop", "--workdir", str(root / "no_run"), "--out", str(root / "out"),
            "--dataset-dir", str(root), *extra]


@pytest.fixture
def onboarded(monkeypatch):
    """The meshes handed to onboarding ({} until it is reached)."""
    seen = {}

    class FakeNets:
        def onboard(self, meshes):
            seen.update(meshes)
            raise _Onboarding

    monkeypatch.setattr(bop_runner, "load_models", lambda args: FakeNets())
    return seen


def test_only_target_objects_are_onboarded(dataset, onboarded):
    with pytest.raises(_Onboarding):
        main(_argv(dataset, "--targets", "bop19"))
    assert onboarded == {k: dataset / "models" / f"obj_{k:06d}.ply" for k in (1, 2)}
    onboarded.clear()
    with pytest.raises(_Onboarding):
        main(_argv(dataset, "--targets", "bop24", "--obj-ids", "2"))
    assert list(onboarded) == [2]


def test_a_target_without_mesh_is_named_before_models_load(dataset, onboarded, capsys):
    # BOP24 targets name images only, so every object of models_info.json is queried.
    with pytest.raises(SystemExit) as e:
        main(_argv(dataset, "--targets", "bop24"))
    err = capsys.readouterr().err
    assert e.value.code == 2
    assert "target objects [3]" in err and str(dataset / "models" / "obj_000003.ply") in err
    assert onboarded == {}
    with pytest.raises(SystemExit):
        main(_argv(dataset, "--targets", "bop24", "--obj-ids", "4"))
    assert "--obj-ids [4] are not in" in capsys.readouterr().err


def test_missing_mesh_message_names_the_file():
    model = bop.ObjectModel(7, 100.0, np.zeros(3), np.ones(3), Symmetries(), None)
    with pytest.raises(FileNotFoundError, match=r"object 7: mesh file obj_000007\.ply is missing"):
        model.vertices()


def test_images_without_detections_are_reported(dataset, monkeypatch, capsys):
    class FakeDetector:
        def detect(self, image, K):
            return Detections([], best_score=0.0517)

    class FakeNets:
        def onboard(self, meshes):
            return []

        def scene_detector(self, objects, **options):
            return FakeDetector()

    monkeypatch.setattr(bop_runner, "load_models", lambda args: FakeNets())
    main(_argv(dataset, "--targets", "bop19"))
    out = capsys.readouterr().out
    assert "scene 1 image 0: 0 detections above threshold 0.1 (best score 0.052)" in out
    assert "1 of 1 images had 0 detections above threshold 0.1" in out
    overlay = cv2.imread(str(dataset / "out" / "overlays" / "000001_000000.png"))
    assert np.any(overlay != 90)  # the caption; the input is a flat grey
