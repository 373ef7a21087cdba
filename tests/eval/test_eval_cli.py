"""`python -m threept_jax.eval` on a generated BOP dataset: 6D CSV and 2D JSON files."""

import json
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from threept_jax.data import bop
from threept_jax.eval.__main__ import main
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
        assert set(scores[t]) == {"ap", "ap50", "ap75"}
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
