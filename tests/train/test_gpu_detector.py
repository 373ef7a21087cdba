"""``scripts/gpu_detector.py subset``: the campaign's records carried to a GPU machine as an
evenly spaced JPEG subset, with the objects they use and nothing else."""

import importlib.util
import json
import pathlib

import cv2
import numpy as np
from array_record.python.array_record_data_source import ArrayRecordDataSource

from threept_jax.data.records import decode_example

ROOT = pathlib.Path(__file__).resolve().parents[2]


def _script():
    spec = importlib.util.spec_from_file_location("gpu_detector", ROOT / "scripts" / "gpu_detector.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _records(folder: pathlib.Path) -> list[dict]:
    source = ArrayRecordDataSource(sorted(str(p) for p in folder.glob("*.array_record")))
    return [decode_example(source[i]) for i in range(len(source))]


def test_subset_keeps_evenly_spaced_records_as_jpeg(toy, tmp_path):
    out = tmp_path / "subset"
    _script().subset(toy, out, images=5, val_images=2, quality=90)
    # By hand: 16 records -> linspace(0, 15, 5) rounded = 0, 4, 8, 11, 15; 6 val -> 0, 5.
    picks = {"train": [0, 4, 8, 11, 15], "val": [0, 5]}
    used = set()
    for split, want in picks.items():
        index = json.loads((out / split / "index.json").read_text())
        assert index["image_format"] == "jpg" and index["num_records"] == len(want)
        assert index["subset_records"] == want
        source, kept = _records(toy / split), _records(out / split)
        for i, ex in zip(want, kept, strict=True):
            ref = source[i]
            np.testing.assert_array_equal(ex["instances"], ref["instances"])
            np.testing.assert_array_equal(ex["obj_id"], ref["obj_id"])
            np.testing.assert_array_equal(ex["bbox_obj"], ref["bbox_obj"])
            # Reference: OpenCV's own JPEG round trip of the source image at quality 90.
            ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(ref["rgb"], cv2.COLOR_RGB2BGR),
                                   [cv2.IMWRITE_JPEG_QUALITY, 90])
            want = cv2.cvtColor(cv2.imdecode(jpg, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
            np.testing.assert_array_equal(ex["rgb"], want)
            used |= {int(o) for o in ex["obj_id"]}
    table = json.loads((out / "objects.json").read_text())
    assert {int(k) for k in table} == used
