"""The training-example record: one annotated image (one view of a scene) as bytes.

``datagen.pack`` writes these records into ArrayRecord shards; the training input pipelines read
them with ``grain.sources.ArrayRecordDataSource`` and ``decode_example``. The format is an
``.npz`` archive (no pickle) whose images are PNG/JPEG-compressed, so a shard is compact and a
record decodes with NumPy and OpenCV alone.

An example is a dict with (M instances, H x W image):

==============  ==================  =====================================================
key             dtype, shape        meaning
==============  ==================  =====================================================
rgb             uint8 [H, W, 3]     the image, RGB
instances       uint16 [H, W]       visible-instance map: 0 background, i + 1 instance i
K               float32 [3, 3]      intrinsics (pixel-centre convention)
T_cam_world     float32 [4, 4]      extrinsics (identity when the dataset has none)
obj_id          int32 [M]           object id of each instance (key of the object table)
T_cam_obj       float32 [M, 4, 4]   pose of each instance, millimetres
bbox_obj        float32 [M, 4]      amodal box, xyxy pixel-edge coordinates
bbox_visib      float32 [M, 4]      box of the visible mask, xyxy pixel-edge coordinates
visib_fract     float32 [M]         visible fraction (BOP ``visib_fract``)
scene_id        int32 []            BOP scene id
im_id           int32 []            BOP image id
source          str []              dataset or generator name
==============  ==================  =====================================================

Visible masks never overlap, so one 16-bit instance map holds all of them losslessly.
"""

from __future__ import annotations

import io
import threading
from typing import Any

import cv2
import numpy as np

FORMAT_VERSION = 1

_ARRAY_FIELDS = {
    "K": (np.float32, (3, 3)),
    "T_cam_world": (np.float32, (4, 4)),
    "obj_id": (np.int32, (-1,)),
    "T_cam_obj": (np.float32, (-1, 4, 4)),
    "bbox_obj": (np.float32, (-1, 4)),
    "bbox_visib": (np.float32, (-1, 4)),
    "visib_fract": (np.float32, (-1,)),
    "scene_id": (np.int32, ()),
    "im_id": (np.int32, ()),
}


def _check(example: dict[str, Any]) -> int:
    missing = [k for k in ("rgb", "instances", *_ARRAY_FIELDS) if k not in example]
    if missing:
        raise KeyError(f"training example is missing fields {missing}; see threept_jax.data.records")
    rgb, inst = np.asarray(example["rgb"]), np.asarray(example["instances"])
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb must be uint8 [H, W, 3], got {rgb.dtype} {rgb.shape}")
    if inst.shape != rgb.shape[:2]:
        raise ValueError(f"instances map {inst.shape} does not match the image {rgb.shape[:2]}")
    m = len(np.asarray(example["obj_id"]).reshape(-1))
    for key, (_, shape) in _ARRAY_FIELDS.items():
        want = tuple(m if s == -1 else s for s in shape)
        got = np.shape(example[key])
        if got != want:
            raise ValueError(f"field {key!r} has shape {got}, expected {want} for {m} instances")
    if inst.max(initial=0) > m:
        raise ValueError(f"instances map refers to instance {int(inst.max()) - 1} but only {m} exist")
    return m


def encode_example(example: dict[str, Any], image_format: str = "png", jpeg_quality: int = 95) -> bytes:
    """Serialise one example (module table) to bytes. ``image_format`` is "png" or "jpg"."""
    _check(example)
    if image_format not in ("png", "jpg"):
        raise ValueError(f"image_format must be 'png' or 'jpg', got {image_format!r}")
    bgr = cv2.cvtColor(np.asarray(example["rgb"]), cv2.COLOR_RGB2BGR)
    params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if image_format == "jpg" else []
    ok, rgb_bytes = cv2.imencode("." + image_format, bgr, params)
    ok2, inst_bytes = cv2.imencode(".png", np.asarray(example["instances"], np.uint16))
    if not (ok and ok2):
        raise RuntimeError("OpenCV failed to encode the example's images")
    arrays = {k: np.asarray(example[k], dtype) for k, (dtype, _) in _ARRAY_FIELDS.items()}
    buf = io.BytesIO()
    np.savez(
        buf,
        version=np.int32(FORMAT_VERSION),
        rgb=rgb_bytes.reshape(-1),
        instances=inst_bytes.reshape(-1),
        source=np.str_(example.get("source", "")),
        **arrays,
    )
    return buf.getvalue()


#: Held while NumPy parses ``.npy`` headers (``np.load`` of records and render banks). NumPy
#: parses them with ``ast.literal_eval``, and CPython 3.11 (seen on 3.11.7) can fail with
#: "SystemError: AST constructor recursion depth mismatch" and abort when several threads do so
#: at once (python/cpython#106905), which grain's read threads would. Parsing a header takes
#: microseconds; image decoding stays outside the lock.
NPY_HEADER_LOCK = threading.Lock()


def decode_example(data: bytes) -> dict[str, Any]:
    """Inverse of ``encode_example``: bytes -> dict of NumPy arrays (module table)."""
    with NPY_HEADER_LOCK, np.load(io.BytesIO(data), allow_pickle=False) as z:
        raw = {k: z[k] for k in ("version", "rgb", "instances", "source", *_ARRAY_FIELDS)}
    version = int(raw["version"])
    if version != FORMAT_VERSION:
        raise ValueError(
            f"record format version {version}, this code reads {FORMAT_VERSION}: re-pack the "
            "shards with `python -m datagen.pack`"
        )
    out = {k: raw[k] for k in _ARRAY_FIELDS}
    bgr = cv2.imdecode(raw["rgb"], cv2.IMREAD_COLOR)
    out["rgb"] = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    out["instances"] = cv2.imdecode(raw["instances"], cv2.IMREAD_UNCHANGED).astype(np.uint16)
    out["source"] = str(raw["source"])
    return out


def visible_masks(example: dict[str, Any]) -> np.ndarray:
    """bool [M, H, W] visible mask of each instance, from the instance map."""
    m = len(example["obj_id"])
    return example["instances"][None] == (np.arange(1, m + 1, dtype=np.uint16)[:, None, None])
