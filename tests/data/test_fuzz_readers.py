"""Fuzz the readers of user files: random bytes and mutations of valid BOP JSON / CSV / PLY.

Every reader must either read the file or raise ``ValueError`` / ``FileNotFoundError`` whose
message names the file, raised by our own code (the innermost frame of the traceback lies in
this project, not inside json, csv, numpy, trimesh or pycocotools), within a per-case time
limit (a hang or a runaway allocation fails the case).
"""

from __future__ import annotations

import contextlib
import json
import pathlib
import signal
import tempfile
import traceback
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from threept_jax.data import bop
from threept_jax.data.ply import load_ply_mesh, load_ply_vertices
from threept_jax.render import load_mesh

PROJECT = pathlib.Path(__file__).resolve().parents[2]
TIME_LIMIT_S = 10
EXAMPLES = 150

R_ID = "1 0 0 0 1 0 0 0 1"
T_GT = [0.0, 0.0, 500.0]
VALID = {
    "scene_gt.json": json.dumps(
        {"0": [{"cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": T_GT, "obj_id": 1}]}),
    "scene_camera.json": json.dumps(
        {"0": {"cam_K": [500, 0, 320, 0, 500, 240, 0, 0, 1], "depth_scale": 1.0}}),
    "scene_gt_info.json": json.dumps(
        {"0": [{"bbox_obj": [1, 2, 30, 40], "bbox_visib": [1, 2, 30, 40], "px_count_all": 100,
                "px_count_valid": 100, "px_count_visib": 90, "visib_fract": 0.9}]}),
    "models_info.json": json.dumps(
        {"1": {"diameter": 100.0, "min_x": -50, "min_y": -50, "min_z": -50, "size_x": 100,
               "size_y": 100, "size_z": 100,
               "symmetries_discrete": [[-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]]}}),
    "test_targets_bop19.json": json.dumps(
        [{"scene_id": 1, "im_id": 0, "obj_id": 1, "inst_count": 1}]),
    "results.csv": (
        "scene_id,im_id,obj_id,score,R,t,time\n"
        f"1,0,1,0.9,{R_ID},0 0 500,1.5\n1,0,2,0.5,{R_ID},10 -5 700.5,1.5\n"),
    "results.json": json.dumps(
        [{"scene_id": 1, "image_id": 0, "category_id": 1, "score": 0.8, "bbox": [1, 2, 3, 4],
          "segmentation": {"size": [4, 5], "counts": [3, 4, 13]}, "time": 1.0}]),
}


def _ply_ascii() -> bytes:
    v = np.array([[0, 0, 0], [40, 0, 0], [0, 40, 0], [0, 0, 40]], np.float64)
    f = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]
    lines = ["ply", "format ascii 1.0", "element vertex 4", "property float x",
             "property float y", "property float z", "element face 4",
             "property list uchar int vertex_indices", "end_header"]
    lines += [" ".join(str(x) for x in row) for row in v]
    lines += ["3 " + " ".join(str(i) for i in row) for row in f]
    return ("\n".join(lines) + "\n").encode()


def _ply_binary() -> bytes:
    v = np.array([[0, 0, 0], [40, 0, 0], [0, 40, 0], [0, 0, 40]], "<f4")
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], "<i4")
    head = ("ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\n"
            "property float y\nproperty float z\nelement face 4\n"
            "property list uchar int vertex_indices\nend_header\n").encode()
    faces = b"".join(np.uint8(3).tobytes() + row.tobytes() for row in f)
    return head + v.tobytes() + faces


VALID_PLY = {"obj_ascii.ply": _ply_ascii(), "obj_binary.ply": _ply_binary()}


def _scene_reader(stem: str):
    def read(path: pathlib.Path):
        scene = bop.BopScene(path.parent)
        return {"scene_gt": lambda: scene.gt, "scene_camera": lambda: scene.cameras,
                "scene_gt_info": lambda: scene.gt_info}[stem]()
    return read


READERS = {
    "scene_gt.json": _scene_reader("scene_gt"),
    "scene_camera.json": _scene_reader("scene_camera"),
    "scene_gt_info.json": _scene_reader("scene_gt_info"),
    "models_info.json": bop.load_models_info,
    "test_targets_bop19.json": bop.load_targets,
    "results.csv": bop.read_pose_results,
    "results.json": bop.read_detection_results,
}
PLY_READERS = {"load_ply_vertices": load_ply_vertices, "load_ply_mesh": load_ply_mesh,
               "load_mesh": load_mesh}


class _Hang(Exception):
    pass


@contextlib.contextmanager
def _time_limit(seconds: int):
    def on_alarm(signum, frame):
        raise _Hang(f"reader ran for more than {seconds} s")
    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def _check_clean(read, path: pathlib.Path, data: bytes) -> None:
    path.write_bytes(data)
    try:
        with _time_limit(TIME_LIMIT_S), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            read(path)
    except (ValueError, FileNotFoundError) as e:
        frame = traceback.extract_tb(e.__traceback__)[-1]
        where = pathlib.Path(frame.filename).resolve()
        assert PROJECT in where.parents and ".venv" not in where.parts, (
            f"error raised inside a dependency ({frame.filename}:{frame.lineno}): {e!r}")
        assert path.name in str(e), f"the message does not name the file: {e}"
    # Anything else (TypeError, KeyError, IndexError, OverflowError, MemoryError, _Hang) fails.


def _mutate(data: bytes, ops: list[tuple[int, int, int]]) -> bytes:
    """Apply (kind, position, value) edits: flip a byte, delete a span, insert bytes, truncate."""
    b = bytearray(data)
    for kind, pos, val in ops:
        if not b:
            break
        i = pos % len(b)
        if kind == 0:
            b[i] = val % 256
        elif kind == 1:
            del b[i:i + 1 + val % 8]
        elif kind == 2:
            b[i:i] = bytes([val % 256]) * (1 + val % 4)
        else:
            del b[i:]
    return bytes(b)


# A JSON mutation: replace one value anywhere in the document by another JSON value.
_JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-2**70, 2**70)
    | st.floats(allow_nan=False) | st.sampled_from([float("nan"), float("inf")])
    | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=17) | st.dictionaries(st.text(max_size=6), inner,
                                                                 max_size=4),
    max_leaves=20)


def _json_paths(doc, prefix=()):
    yield prefix
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _json_paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _json_paths(v, prefix + (i,))


def _replace(doc, path, value):
    if not path:
        return value
    doc = json.loads(json.dumps(doc))
    node = doc
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    return doc


class _Folders:
    """One scene folder per file kind, so a reader never meets another case's broken file."""

    def __init__(self, root: pathlib.Path):
        self.root = root

    def __truediv__(self, name: str) -> pathlib.Path:
        scene = self.root / name.replace(".", "_") / "000001"
        scene.mkdir(parents=True, exist_ok=True)
        return scene / name


@pytest.fixture(scope="module")
def folder():
    with tempfile.TemporaryDirectory() as d:
        yield _Folders(pathlib.Path(d))


SETTINGS = settings(max_examples=EXAMPLES, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture,
                                           HealthCheck.too_slow])
_OPS = st.lists(st.tuples(st.integers(0, 3), st.integers(0, 10**6), st.integers(0, 10**6)),
                min_size=1, max_size=6)


@pytest.mark.parametrize("name", sorted(READERS))
def test_valid_files_read(folder, name):
    """The seeds are valid: the readers accept them (so mutations start from real files)."""
    p = folder / name
    p.write_text(VALID[name])
    READERS[name](p)


@pytest.mark.parametrize("name", sorted(READERS))
@SETTINGS
@given(data=st.binary(max_size=300))
def test_random_bytes_bop_files(folder, name, data):
    _check_clean(READERS[name], folder / name, data)


@pytest.mark.parametrize("name", sorted(READERS))
@SETTINGS
@given(ops=_OPS)
def test_mutated_bytes_bop_files(folder, name, ops):
    _check_clean(READERS[name], folder / name, _mutate(VALID[name].encode(), ops))


@pytest.mark.parametrize("name", sorted(n for n in READERS if n.endswith(".json")))
@SETTINGS
@given(st.data())
def test_mutated_json_structure(folder, name, data):
    doc = json.loads(VALID[name])
    path = data.draw(st.sampled_from(list(_json_paths(doc))))
    value = data.draw(_JSON_VALUES)
    _check_clean(READERS[name], folder / name, json.dumps(_replace(doc, path, value)).encode())


@pytest.mark.parametrize("reader", sorted(PLY_READERS))
@pytest.mark.parametrize("name", sorted(VALID_PLY))
def test_valid_ply_read(folder, reader, name):
    p = folder / name
    p.write_bytes(VALID_PLY[name])
    PLY_READERS[reader](p)


@pytest.mark.parametrize("reader", sorted(PLY_READERS))
@SETTINGS
@given(data=st.binary(max_size=400))
def test_random_bytes_ply(folder, reader, data):
    _check_clean(PLY_READERS[reader], folder / "obj_random.ply", b"ply\n" + data)


@pytest.mark.parametrize("reader", sorted(PLY_READERS))
@pytest.mark.parametrize("name", sorted(VALID_PLY))
@SETTINGS
@given(ops=_OPS)
def test_mutated_ply(folder, reader, name, ops):
    _check_clean(PLY_READERS[reader], folder / name, _mutate(VALID_PLY[name], ops))
