"""BOP result files: the 6D CSV and 2D JSON readers refuse malformed input with ValueError
naming the file and the line or entry; RLE counts are checked against a NumPy run-length
reference."""

import json

import numpy as np
import pytest

from threept_jax.data import bop
from threept_jax.data.bop.results import _string_rle_counts, validate_rle

HEADER = "scene_id,im_id,obj_id,score,R,t,time\n"
EYE = " ".join(map(str, np.eye(3).reshape(-1)))


def _runs(mask):
    """Uncompressed COCO counts (column-major runs, starting with zeros) by NumPy."""
    flat = mask.ravel(order="F").astype(int)
    change = np.flatnonzero(np.diff(np.concatenate([[0], flat, [2]])) != 0)
    return np.diff(np.concatenate([[0], change]))


@pytest.mark.parametrize("shape, p", [((37, 53), 0.6), ((480, 640), 0.999), ((5, 5), 0.0),
                                      ((5, 5), 1.1), ((3000, 4000), 0.99999)])
def test_compressed_rle_counts_match_numpy_runs(shape, p):
    m = np.random.default_rng(0).random(shape) > p
    rle = bop.mask_to_rle(m)
    np.testing.assert_array_equal(_string_rle_counts(rle["counts"]), _runs(m))
    assert validate_rle(rle, "x", shape) == shape


def _det_file(tmp_path, **entry):
    d = {"scene_id": 1, "image_id": 4, "category_id": 7, "score": 0.5, "bbox": [1, 2, 3, 4]}
    d.update(entry)
    p = tmp_path / "dets.json"
    p.write_text(json.dumps([d]))
    return p


GOOD = bop.mask_to_rle(np.random.default_rng(1).random((48, 64)) > 0.5)


@pytest.mark.parametrize(
    "seg, msg",
    [
        (dict(GOOD, counts=GOOD["counts"][:-3]), "counts sum to"),  # truncated string
        (dict(GOOD, counts=GOOD["counts"][:-1] + "x"), "not a valid COCO compressed RLE"),
        (dict(GOOD, counts="\u00e9" + GOOD["counts"]), "not a valid COCO compressed RLE"),
        ({"counts": [10, -4, 3066], "size": [48, 64]}, "must not be negative"),
        ({"counts": [10, 20], "size": [48, 64]}, "counts sum to 30"),
        ({"counts": [10, 2.5], "size": [48, 64]}, "must be integers"),
        ({"counts": GOOD["counts"], "size": [48]}, r"\[height, width\]"),
        ({"counts": GOOD["counts"], "size": [48.0, 64.0]}, r"\[height, width\]"),
        ({"counts": {"a": 1}, "size": [48, 64]}, "string or a list"),
        ({"size": [48, 64]}, "COCO RLE dict"),
        ([[1, 2, 3, 4, 5, 6]], "COCO RLE dict"),  # polygons
    ],
)
def test_2d_reader_refuses_broken_rle(tmp_path, seg, msg):
    p = _det_file(tmp_path, segmentation=seg)
    with pytest.raises(ValueError, match=rf"dets.json entry 0 \(scene 1, image 4\).*{msg}"):
        bop.read_detection_results(p)


def test_2d_reader_accepts_list_counts_and_empty_fields(tmp_path):
    m = np.random.default_rng(2).random((6, 5)) > 0.5
    p = _det_file(tmp_path, segmentation={"counts": _runs(m).tolist(), "size": [6, 5]}, bbox=[])
    (d,) = bop.read_detection_results(p)
    assert d.bbox is None
    np.testing.assert_array_equal(bop.rle_to_mask(d.segmentation), m)


@pytest.mark.parametrize(
    "entry, msg",
    [
        ({"bbox": [0, 0, -3, 4]}, r"bbox \[0.0, 0.0, -3.0, 4.0\] has negative size"),
        ({"bbox": [0, float("nan"), 3, 4]}, "bbox must be finite"),
        ({"bbox": [0, 0, 3, "4"]}, "bbox must be a number"),
        ({"bbox": "abcd"}, r"bbox must be \[x, y, w, h\]"),
        ({"score": float("nan")}, "score must be finite"),
        ({"score": "high"}, "score must be a number"),
        ({"score": True}, "score must be a number"),
        ({"time": float("inf")}, "time .* must be finite"),
    ],
)
def test_2d_reader_refuses_bad_boxes_scores_and_times(tmp_path, entry, msg):
    p = _det_file(tmp_path, **entry)
    with pytest.raises(ValueError, match=rf"dets.json entry 0 \(scene 1, image 4\): {msg}"):
        bop.read_detection_results(p)


@pytest.mark.parametrize(
    "row, msg",
    [
        (f"1,2,3,nan,{EYE},1 2 3,0.1", "score must be finite"),
        (f"1,2,3,inf,{EYE},1 2 3,0.1", "score must be finite"),
        (f"1,2,3,0.5,{EYE},1 nan 3,0.1", "t has non-finite values"),
        (f"1,2,3,0.5,{EYE},1 2 -inf,0.1", "t has non-finite values"),
        (f"1,2,3,0.5,{EYE},1 2 3,nan", "time .* must be finite"),
        ("1,2,3,0.5,nan 0 0 0 1 0 0 0 1,1 2 3,0.1", "rotation has non-finite entries"),
    ],
)
def test_pose_csv_refuses_non_finite_values(tmp_path, row, msg):
    p = tmp_path / "r.csv"
    p.write_text(HEADER + f"1,2,3,0.5,{EYE},1 2 3,0.1\n" + row + "\n")
    with pytest.raises(ValueError, match=f"r.csv:3: {msg}"):
        bop.read_pose_results(p)


def test_pose_csv_without_header_is_read_and_rotation_atol_checked(tmp_path):
    p = tmp_path / "r.csv"
    p.write_text(f"1,2,3,0.5,{EYE},1 2 3,0.1\r\n")  # the toolkit reads headerless files too
    assert len(bop.read_pose_results(p)) == 1
    with pytest.raises(ValueError, match="rotation_atol must be a positive"):
        bop.read_pose_results(p, rotation_atol=0.0)


MALFORMED = [
    ("r.csv", bytes(range(256)) * 3, r"r.csv:2: not UTF-8"),
    ("r.csv", HEADER.encode() + b"1,2,3,0.5,\xff\xfe,1 2 3,0.1\n", r"r.csv:2: not UTF-8"),
    ("r.csv", b"scene,image,object\n1,2,3\n", r"r.csv:1: expected 7"),
    ("r.csv", HEADER.encode() + b"a,b,c,d,e,f,g\n", r"r.csv:2: could not parse"),
    ("r.csv", HEADER.encode() + b"1" * 5000 + b",2,3,0.5,1,2,3\n", r"r.csv:2: could not parse"),
    ("d.json", bytes(range(256)) * 3, r"d.json:2: not UTF-8"),
    ("d.json", b'[{"scene_id": 1', r"d.json is not valid JSON"),
    ("d.json", b"[" * 100000 + b"]" * 100000, r"d.json: JSON nested too deeply"),
    ("d.json", b'{"scene_id": 1}', r"d.json: a 2D results file must be a JSON list"),
    ("d.json", b"[1, 2]", r"d.json entry 0: a detection must be a JSON object"),
    ("d.json", b'[{"scene_id": 1, "image_id": 2, "category_id": 3}]', r"entry 0: missing 'score'"),
    ("d.json", b"[" + b"9" * 5000 + b"]", r"d.json is not valid JSON"),
]


@pytest.mark.parametrize("name, data, msg", MALFORMED)
def test_malformed_results_files_raise_value_error_naming_the_file(tmp_path, name, data, msg):
    p = tmp_path / name
    p.write_bytes(data)
    read = bop.read_pose_results if name.endswith(".csv") else bop.read_detection_results
    with pytest.raises(ValueError, match=msg):
        read(p)
