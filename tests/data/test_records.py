"""Training-example records: exact round trip through an ArrayRecord shard read by grain."""

import grain
import numpy as np
import pytest
from array_record.python.array_record_module import ArrayRecordWriter

from threept_jax.data import records


def _example(rng, m=3, h=24, w=32):
    inst = np.zeros((h, w), np.uint16)
    inst[2:10, 3:12] = 1
    inst[12:20, 5:9] = 3  # instance 1 (id 2) fully occluded: absent from the map
    T = np.tile(np.eye(4, dtype=np.float32), (m, 1, 1))
    T[:, :3, 3] = rng.normal(0, 100, (m, 3))
    return {
        "rgb": rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
        "instances": inst,
        "K": np.array([[50.0, 0, 15.5], [0, 52.0, 11.5], [0, 0, 1]], np.float32),
        "T_cam_world": np.eye(4, dtype=np.float32),
        "obj_id": np.array([4, 7, 4], np.int32),
        "T_cam_obj": T,
        "bbox_obj": rng.uniform(0, 20, (m, 4)).astype(np.float32),
        "bbox_visib": rng.uniform(0, 20, (m, 4)).astype(np.float32),
        "visib_fract": np.array([1.0, 0.0, 0.5], np.float32),
        "scene_id": np.int32(3),
        "im_id": np.int32(17),
        "source": "unit-test",
    }


def test_roundtrip_through_arrayrecord_and_grain(tmp_path):
    rng = np.random.default_rng(0)
    examples = [_example(rng) for _ in range(5)]
    path = str(tmp_path / "shard-00000-of-00001.array_record")
    writer = ArrayRecordWriter(path, "group_size:1")
    for ex in examples:
        writer.write(records.encode_example(ex))
    writer.close()
    source = grain.sources.ArrayRecordDataSource([path])
    assert len(source) == 5
    ds = grain.MapDataset.source(source).map(records.decode_example)
    for ex, got in zip(examples, ds):
        for key, value in ex.items():
            if key == "source":
                assert got[key] == value
            else:
                np.testing.assert_array_equal(got[key], value, err_msg=key)
                assert got[key].dtype == np.asarray(value).dtype or key in ("scene_id", "im_id"), key
    masks = records.visible_masks(got)
    assert masks.shape == (3, 24, 32) and masks[0].sum() == 72 and masks[1].sum() == 0 and masks[2].sum() == 32


def test_jpeg_is_lossy_but_close():
    ex = _example(np.random.default_rng(1))
    ex["rgb"] = np.full_like(ex["rgb"], 128)
    got = records.decode_example(records.encode_example(ex, image_format="jpg"))
    assert np.abs(got["rgb"].astype(int) - 128).max() <= 2
    np.testing.assert_array_equal(got["instances"], ex["instances"])


def test_bad_examples_raise_clear_errors():
    ex = _example(np.random.default_rng(2))
    with pytest.raises(ValueError, match="T_cam_obj"):
        records.encode_example({**ex, "T_cam_obj": ex["T_cam_obj"][:2]})
    with pytest.raises(KeyError, match="missing fields"):
        records.encode_example({k: v for k, v in ex.items() if k != "K"})
    with pytest.raises(ValueError, match="only 3 exist"):
        records.encode_example({**ex, "instances": np.full_like(ex["instances"], 9)})
    with pytest.raises(ValueError, match="uint8"):
        records.encode_example({**ex, "rgb": ex["rgb"].astype(np.float32)})
