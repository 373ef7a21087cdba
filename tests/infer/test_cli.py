"""The inference CLI's camera arguments: parsed into Cameras, bad ones named."""

import json

import numpy as np
import pytest

from infer.cli import _cameras, build_parser


def _args(tmp_path, *extra):
    return build_parser().parse_args(["images", "--workdir", str(tmp_path), "--out",
                                      str(tmp_path / "out"), "--mesh", "1=a.ply",
                                      "--image", "a.png", *extra])


def test_k_flags_and_camera_files_become_cameras(tmp_path):
    (cam,) = _cameras(_args(tmp_path, "--K", "600,610,319.5,239.5"), 1)
    np.testing.assert_array_equal(cam.K, [[600, 0, 319.5], [0, 610, 239.5], [0, 0, 1]])
    assert cam.T_cam_world is None
    T = np.eye(4)
    T[:3, 3] = [10.0, -5.0, 700.0]
    path = tmp_path / "cams.json"
    path.write_text(json.dumps([{"K": cam.K.tolist(), "T_cam_world": T.tolist()}]))
    (rig,) = _cameras(_args(tmp_path, "--cameras", str(path)), 1)
    np.testing.assert_array_equal(rig.T_cam_world, T)


def test_bad_camera_arguments_name_the_problem(tmp_path):
    path = tmp_path / "cams.json"
    path.write_text(json.dumps([{"T_cam_world": np.eye(4).tolist()}]))
    with pytest.raises(SystemExit, match='camera 0 has no "K"'):
        _cameras(_args(tmp_path, "--cameras", str(path)), 1)
    with pytest.raises(SystemExit, match="four numbers"):
        _cameras(_args(tmp_path, "--K", "600,610,319.5"), 1)
    with pytest.raises(SystemExit, match="one --K"):
        _cameras(_args(tmp_path), 1)
