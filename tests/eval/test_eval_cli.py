"""`python -m threept_jax.eval` on a generated BOP dataset: 6D CSV and 2D JSON files."""

import json
import os
import subprocess
import sys
import warnings

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from threept_jax.data import bop
from threept_jax.eval.__main__ import main
from threept_jax.eval.bop_eval import evaluate_detection_results, evaluate_results_file
from threept_jax.testing.bop_synthetic import SyntheticInstance, write_synthetic_dataset

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
KEYS_6D = {
    "ap",
    "ap_mssd",
    "ap_mspd",
    "ap_mm",
    "ar_mssd",
    "ar_mspd",
    "per_object",
    "num_estimates",
    "num_gt",
}


def _pose(x, y, z, seed):
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = [x, y, z]
    return T


@pytest.fixture(scope="module")
def dataset(tmp_path_factory, bop_models_dir):
    itodd = bop.load_models(bop_models_dir / "itodd" / "models")
    scenes = {
        4: {
            0: [
                SyntheticInstance(3, _pose(-80, 0, 800, 1)),
                SyntheticInstance(19, _pose(60, 0, 700, 2)),
                SyntheticInstance(19, _pose(0, 90, 900, 3), 0.05),
            ],
            1: [SyntheticInstance(3, _pose(0, 0, 600, 4))],
        }
    }
    root = write_synthetic_dataset(
        tmp_path_factory.mktemp("cli") / "itodd_mini", {3: itodd[3], 19: itodd[19]}, scenes, K
    )
    return root, scenes


def test_cli_6d(dataset, tmp_path, capsys):
    root, scenes = dataset
    ests = []
    for sid, ims in scenes.items():
        for iid, insts in ims.items():
            for inst in insts:
                T = inst.T_cam_obj.copy()
                if (iid, inst.obj_id) == (1, 3):
                    T[0, 3] += 3.0  # AP-mm: 3 mm passes 9 of the 10 thresholds
                ests.append(bop.PoseEstimate(sid, iid, inst.obj_id, 0.8, T[:3, :3], T[:3, 3], 0.5))
    res = tmp_path / "m_itodd-test.csv"
    bop.write_pose_results(res, ests)
    out = tmp_path / "scores.json"
    assert (
        main(
            [
                "--dataset-dir",
                str(root),
                "--split",
                "test",
                "--results",
                str(res),
                "--out",
                str(out),
                "--models-subdir",
                "models",
            ]
        )
        == 0
    )
    scores = json.loads(out.read_text())
    assert set(scores) == KEYS_6D
    assert scores["ap_mssd"] == 1.0 and scores["ar_mssd"] == 1.0 and scores["num_gt"] == 3
    # Object 3 has two GT, one found at every mm threshold and one at 9 of 10: per threshold
    # AP is 1 (both found) or 51/101 (recall 1/2); object 19's AP-mm is 1.
    ap3 = (9 * 1.0 + 51 / 101) / 10
    assert scores["per_object"]["3"]["ap_mm"] == pytest.approx(ap3)
    assert scores["ap_mm"] == pytest.approx((ap3 + 1.0) / 2)
    for v in [scores[k] for k in KEYS_6D - {"per_object", "num_estimates", "num_gt"}]:
        assert 0.0 <= v <= 1.0
    assert "ap_mm" in capsys.readouterr().out


def test_cli_2d(dataset, tmp_path):
    root, scenes = dataset
    sc = bop.BopDataset(root).split("test").scene(4)
    dets = []
    for iid, insts in scenes[4].items():
        for j, inst in enumerate(insts):
            full, vis = sc.mask(iid, j), sc.mask_visib(iid, j)
            box = cv2.boundingRect(full.astype(np.uint8))
            dets.append(
                bop.Detection2D(4, iid, inst.obj_id, 0.9 - 0.1 * j, box, bop.mask_to_rle(vis))
            )
    res = tmp_path / "m_itodd-test.json"
    bop.write_detection_results(res, dets)
    out = tmp_path / "scores2d.json"
    assert main(["--dataset-dir", str(root), "--results", str(res), "--out", str(out)]) == 0
    scores = json.loads(out.read_text())
    assert set(scores) == {"bbox", "segm"}
    for t in ("bbox", "segm"):
        assert set(scores[t]) == {"ap", "ap50", "ap75", "f1", "f1_threshold"}
        assert scores[t]["ap"] == pytest.approx(1.0)


def test_cli_module_entry_point_and_errors(dataset, tmp_path):
    root, _ = dataset
    bad = tmp_path / "bad.csv"
    bad.write_text("scene_id,im_id,obj_id,score,R,t,time\n4,0,3,0.5,1 0 0 0 1 0 0 0 1,0 0 1\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "threept_jax.eval",
            "--dataset-dir",
            str(root),
            "--results",
            str(bad),
            "--out",
            str(tmp_path / "o.json"),
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert r.returncode == 2 and "expected 7 comma-separated columns" in r.stderr
    assert (
        main(
            [
                "--dataset-dir",
                str(tmp_path / "missing"),
                "--results",
                str(bad),
                "--out",
                str(tmp_path / "o.json"),
            ]
        )
        == 2
    )


def _write_6d(path, scenes, t_scale=1.0, score=0.8, round_R=None):
    ests = []
    for sid, ims in scenes.items():
        for iid, insts in ims.items():
            for inst in insts:
                T = inst.T_cam_obj
                ests.append(
                    bop.PoseEstimate(sid, iid, inst.obj_id, score, T[:3, :3], T[:3, 3], 0.5)
                )
    bop.write_pose_results(path, ests)
    if round_R is not None or t_scale != 1.0:  # rewrite columns the writer would refuse
        lines = path.read_text().splitlines()
        for n in range(1, len(lines)):
            c = lines[n].split(",")
            if round_R is not None:
                c[4] = " ".join(str(round(float(v), round_R)) for v in c[4].split())
            c[5] = " ".join(repr(float(v) * t_scale) for v in c[5].split())
            lines[n] = ",".join(c)
        path.write_text("\n".join(lines) + "\n")
    return path


def _cli(root, res, tmp_path, *extra):
    return main(["--dataset-dir", str(root), "--results", str(res), "--out",
                 str(tmp_path / "o.json"), "--models-subdir", "models", *extra])


@pytest.mark.parametrize(
    "flag, value",
    [
        ("--image-width", "0"),
        ("--image-width", "-640"),
        ("--max-estimates-per-image", "0"),
        ("--rotation-atol", "0"),
        ("--rotation-atol", "nan"),
    ],
)
def test_cli_refuses_bad_numeric_options(dataset, tmp_path, capsys, flag, value):
    root, scenes = dataset
    res = _write_6d(tmp_path / "m_itodd-test.csv", scenes)
    assert _cli(root, res, tmp_path, flag, value) == 2
    assert f"error: {flag} must be" in capsys.readouterr().err


@pytest.mark.parametrize(
    "kwargs, msg",
    [
        (dict(image_width=0), "image_width must be an integer >= 1"),
        (dict(image_width=-640), "image_width must be an integer >= 1"),
        (dict(image_width=640.5), "image_width must be an integer >= 1"),
        (dict(max_estimates_per_image=0), "max_estimates_per_image must be an integer >= 1"),
        (dict(rotation_atol=0.0), "rotation_atol must be a finite number > 0"),
    ],
)
def test_api_refuses_bad_numeric_arguments(dataset, tmp_path, kwargs, msg):
    root, scenes = dataset
    res = _write_6d(tmp_path / "m_itodd-test.csv", scenes)
    with pytest.raises(ValueError, match=msg):
        evaluate_results_file(root, res, models_subdir="models", **kwargs)


def test_cli_rotation_atol(dataset, tmp_path, capsys):
    root, scenes = dataset
    # Rounded to 2 decimals, the estimates' R deviate from orthonormal by ~5e-3.
    res = _write_6d(tmp_path / "m_itodd-test.csv", scenes, round_R=2)
    assert _cli(root, res, tmp_path) == 2
    assert "m_itodd-test.csv:2: rotation" in capsys.readouterr().err
    assert _cli(root, res, tmp_path, "--rotation-atol", "0.02") == 0


def test_metre_translations_are_warned_about(dataset, tmp_path):
    root, scenes = dataset
    res = _write_6d(tmp_path / "m_itodd-test.csv", scenes, t_scale=1e-3)
    with pytest.warns(UserWarning, match="translations look like metres"):
        s = evaluate_results_file(root, res, models_subdir="models")
    assert s.ap_mssd == 0.0
    res = _write_6d(tmp_path / "m_itodd-test.csv", scenes)
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*look like metres")
        assert evaluate_results_file(root, res, models_subdir="models").ap_mssd == 1.0


def test_cli_refuses_a_nan_score(dataset, tmp_path, capsys):
    root, scenes = dataset
    res = _write_6d(tmp_path / "m_itodd-test.csv", scenes, score=float("nan"))
    assert _cli(root, res, tmp_path) == 2
    assert "m_itodd-test.csv:2: score must be finite" in capsys.readouterr().err


def _dets_2d(root, scenes):
    sc = bop.BopDataset(root).split("test").scene(4)
    dets = []
    for iid, insts in scenes[4].items():
        for j, inst in enumerate(insts):
            box = cv2.boundingRect(sc.mask(iid, j).astype(np.uint8))
            dets.append(bop.Detection2D(4, iid, inst.obj_id, 0.9 - 0.1 * j, box,
                                        bop.mask_to_rle(sc.mask_visib(iid, j))))
    return dets


def test_2d_rle_is_checked_against_the_image_size(dataset, tmp_path):
    root, scenes = dataset
    dets = _dets_2d(root, scenes)
    small = bop.mask_to_rle(np.ones((240, 320), bool))  # a valid RLE, for another image size
    bad = [dets[0], bop.Detection2D(4, 1, 3, 0.5, None, small)]
    with pytest.raises(ValueError, match=r"detection 1 \(scene 4, image 1\).*differs from the "
                                         r"image size \[480, 640\]"):
        evaluate_detection_results(root, bad)
    res = tmp_path / "m_itodd-test.json"
    bop.write_detection_results(res, bad)
    with pytest.raises(ValueError, match="differs from the image size"):
        evaluate_results_file(root, res)


def test_2d_truncated_rle_is_refused_by_the_evaluator(dataset):
    # A truncated RLE used to hang pycocotools' IoU forever.
    root, scenes = dataset
    dets = _dets_2d(root, scenes)
    seg = dict(dets[0].segmentation)
    seg["counts"] = seg["counts"][: len(seg["counts"]) // 2]
    bad = [bop.Detection2D(4, 0, 3, 0.9, None, seg)]
    with pytest.raises(ValueError, match=r"detection 0 \(scene 4, image 0\).*counts sum to"):
        evaluate_detection_results(root, bad)


def test_2d_list_counts_are_evaluated(dataset, tmp_path):
    # Uncompressed counts (the toolkit's binary_mask_to_rle) score as the compressed ones.
    root, scenes = dataset
    dets = []
    for d in _dets_2d(root, scenes):
        m = bop.rle_to_mask(d.segmentation).ravel(order="F").astype(int)
        change = np.flatnonzero(np.diff(np.concatenate([[0], m, [2]])) != 0)
        counts = np.diff(np.concatenate([[0], change])).tolist()
        dets.append(bop.Detection2D(d.scene_id, d.im_id, d.obj_id, d.score, d.bbox,
                                    {"counts": counts, "size": d.segmentation["size"]}))
    res = tmp_path / "m_itodd-test.json"
    bop.write_detection_results(res, dets)
    assert evaluate_results_file(root, res)["segm"]["ap"] == pytest.approx(1.0)
