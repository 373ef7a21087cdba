"""``python -m train.templates_score --cell``: what it refuses, with what to do (the fit itself
is tests/pipeline/test_shape_search.py's ``fit_part_weights`` against known models, and its
file's use is ``test_a_cells_score_calibration_scores_its_parts``)."""

import json

import pytest
import trimesh

from infer.cli import build_parser
from infer.options import load_models
from train import templates_score


def _dataset(root, splits):
    (root / "models").mkdir(parents=True)
    trimesh.creation.box((20, 20, 20)).export(root / "models" / "obj_000001.ply")
    (root / "models" / "models_info.json").write_text(json.dumps(
        {"1": {"diameter": 34.6, "min_x": -10, "min_y": -10, "min_z": -10, "size_x": 20,
               "size_y": 20, "size_z": 20}}))
    for s in splits:
        (root / s).mkdir()
    return root


def test_a_cell_calibration_names_what_is_wrong_with_its_data(tmp_path):
    with pytest.raises(SystemExit, match="not a BOP dataset"):
        templates_score.main(["--cell", str(tmp_path)])
    two = _dataset(tmp_path / "two", ["train_pbr", "val_pbr"])
    with pytest.raises(SystemExit, match="name one with --split"):
        templates_score.main(["--cell", str(two)])
    with pytest.raises(SystemExit, match="no split 'test'"):
        templates_score.main(["--cell", str(two), "--split", "test"])
    with pytest.raises(SystemExit, match="no scenes"):
        templates_score.main(["--cell", str(two), "--split", "train_pbr"])
    with pytest.raises(SystemExit):  # argparse: --images below 1
        templates_score.main(["--cell", str(two), "--images", "0"])


def test_a_calibration_is_refused_with_3pt(tmp_path):
    args = build_parser().parse_args(["images", "--detector", "3pt", "--templates-score",
                                      str(tmp_path / "s.json"), "--out", str(tmp_path),
                                      "--mesh", "1=x.ply", "--K", "1,1,0,0", "--image", "i.png"])
    with pytest.raises(ValueError, match="--templates-score calibrates the templates"):
        load_models(args)
