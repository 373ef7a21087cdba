"""BOP result files: the 6D CSV and the 2D COCO JSON with RLE masks."""

from __future__ import annotations

import math
import pathlib
import re
from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from threept_jax.data.bop.json_format import _load_json, _read_text, _short, write_json_atomic
from threept_jax.data.bop.types import POSE_CSV_HEADER, Detection2D, PoseEstimate
from threept_jax.data.files import atomic_write_bytes
from threept_jax.geometry.validate import validate_rotation


def write_pose_results(path, estimates: Iterable[PoseEstimate], time_tol: float = 1e-3) -> None:
    """Write a BOP 6D results CSV (atomic). Every image must carry one time (s) for all its
    estimates (-1 when unknown), as the toolkit requires."""
    lines = [POSE_CSV_HEADER]
    times: dict[tuple[int, int], float] = {}
    for e in estimates:
        key = (int(e.scene_id), int(e.im_id))
        t = float(e.time)
        if key in times and abs(times[key] - t) > time_tol:
            raise ValueError(
                f"scene {key[0]} image {key[1]}: estimates carry different times "
                f"({times[key]} and {t}); BOP wants one time per image (the whole image's "
                "processing time) on every row of that image"
            )
        times.setdefault(key, t)
        R = validate_rotation(e.R, f"estimate scene {key[0]} im {key[1]} obj {e.obj_id}")
        lines.append(
            ",".join(
                [
                    str(key[0]),
                    str(key[1]),
                    str(int(e.obj_id)),
                    repr(float(e.score)),
                    " ".join(repr(float(v)) for v in R.reshape(-1)),
                    " ".join(repr(float(v)) for v in np.reshape(e.t, 3)),
                    repr(times[key]),
                ]
            )
        )
    atomic_write_bytes(pathlib.Path(path), ("\n".join(lines) + "\n").encode())


def _finite(value: float, what: str, where: str) -> float:
    if not math.isfinite(value):
        raise ValueError(f"{where}: {what} must be finite, got {value}")
    return value


def read_pose_results(path, rotation_atol: float = 1e-3) -> list[PoseEstimate]:
    """Read a BOP 6D results CSV (`inout.load_bop_results`, version bop19), validating it.

    The header line is optional, as in the toolkit. R (row-major) must be orthonormal within
    ``rotation_atol`` (largest entry of |R R^T - I|) with det +1; R, t, score and time must be
    finite. Every problem raises ValueError naming the file and line."""
    path = pathlib.Path(path)
    if not (isinstance(rotation_atol, (int, float)) and 0 < rotation_atol < math.inf):
        raise ValueError(
            f"rotation_atol must be a positive finite tolerance, got {_short(rotation_atol)}"
        )
    text = _read_text(path, "6D results CSV")
    out = []
    for line_no, line in enumerate(re.split(r"\r\n|\r|\n", text), start=1):
        if line_no == 1 and POSE_CSV_HEADER in line:
            continue
        if not line.strip():
            continue
        elems = line.split(",")
        where = f"{path}:{line_no}"
        if len(elems) != 7:
            raise ValueError(
                f"{where}: expected 7 comma-separated columns ({POSE_CSV_HEADER}), got "
                f"{len(elems)}; R and t must be space-separated inside their column"
            )
        try:
            sid, iid, oid = int(elems[0]), int(elems[1]), int(elems[2])
            score = float(elems[3])
            R = np.array([float(v) for v in elems[4].split()], np.float64)
            t = np.array([float(v) for v in elems[5].split()], np.float64)
            tm = float(elems[6])
        except ValueError as e:
            raise ValueError(f"{where}: could not parse the row ({_short(str(e), 200)})") from None
        if t.shape != (3,):
            raise ValueError(f"{where}: t must have 3 values (mm), got {t.size}")
        _finite(score, "score", where)
        _finite(tm, "time (s, -1 when unknown)", where)
        if not np.all(np.isfinite(t)):
            raise ValueError(f"{where}: t has non-finite values: {t.tolist()}")
        R = validate_rotation(R, where, rotation_atol)
        out.append(PoseEstimate(sid, iid, oid, score, R, t, tm))
    return out


def check_consistent_times(estimates: Iterable[PoseEstimate], tol: float = 1e-3) -> None:
    """Raise if one image's estimates carry different times (`inout.check_consistent_timings`)."""
    times: dict[tuple[int, int], float] = {}
    for e in estimates:
        key = (e.scene_id, e.im_id)
        if key in times and abs(times[key] - e.time) > tol:
            raise ValueError(
                f"the running time for scene {key[0]} and image {key[1]} is not the same for all "
                f"estimates ({times[key]} and {e.time}); write one time per image"
            )
        times.setdefault(key, e.time)


def top_estimates_per_image(
    estimates: Sequence[PoseEstimate], max_per_image: int | None
) -> list[PoseEstimate]:
    """Keep the ``max_per_image`` highest-scoring estimates of each image, grouped by image in
    order of first appearance (stable sort), exactly as `inout.load_bop_results` does."""
    if max_per_image is None:
        return list(estimates)
    groups: dict[tuple[int, int], list[PoseEstimate]] = {}
    for e in estimates:
        groups.setdefault((e.scene_id, e.im_id), []).append(e)
    out = []
    for g in groups.values():
        out.extend(sorted(g, key=lambda e: e.score, reverse=True)[:max_per_image])
    return out


# ----------------------------------------------------------------------------- 2D results
def mask_to_rle(mask: np.ndarray) -> dict:
    """COCO RLE of a binary mask [H, W]: {"counts": compressed str, "size": [H, W]}."""
    from pycocotools import mask as mask_utils

    m = np.asfortranarray(np.asarray(mask, dtype=np.uint8))
    rle = mask_utils.encode(m)
    return {"counts": rle["counts"].decode("ascii"), "size": [int(m.shape[0]), int(m.shape[1])]}


# A mask larger than this many pixels is refused: pycocotools holds sizes and counts in
# 32-bit unsigned integers.
MAX_RLE_PIXELS = (1 << 31) - 1
# pycocotools writes a count difference (at most 2^32 in magnitude, signed) in at most 7
# characters of 5 bits each.
_MAX_RLE_TOKEN_CHARS = 7


def _string_rle_counts(s: str) -> np.ndarray | None:
    """Counts of a COCO compressed RLE string, decoded as pycocotools' ``rleFrString`` does
    (5-bit groups with a continuation bit, sign extension, each count from the third on
    stored as a difference to the count two before), or None when the string is not a valid
    encoding (a character outside '0'..'o', a truncated or over-long value)."""
    if not s.isascii():
        return None
    c = np.frombuffer(s.encode("ascii"), np.uint8).astype(np.int64) - 48
    if c.size == 0:
        return np.zeros(0, np.int64)
    if c.min() < 0 or c.max() > 63 or c[-1] & 0x20:
        return None
    ends = np.flatnonzero((c & 0x20) == 0)
    starts = np.concatenate([[0], ends[:-1] + 1])
    lengths = ends - starts + 1
    if lengths.max() > _MAX_RLE_TOKEN_CHARS:
        return None
    pos = np.arange(c.size) - np.repeat(starts, lengths)
    x = np.add.reduceat((c & 0x1F) << (5 * pos), starts)
    x -= ((c[ends] & 0x10) != 0) << (5 * lengths)  # sign extension of the last 5-bit group
    counts = x.copy()
    counts[1::2] = np.cumsum(x[1::2])
    counts[2::2] = np.cumsum(x[2::2])
    return counts


def validate_rle(rle, where: str, image_hw: tuple[int, int] | None = None) -> tuple[int, int]:
    """Check a COCO RLE ``{"counts", "size": [h, w]}`` and return (h, w).

    ``counts`` is a compressed string (pycocotools) or a list of integers (uncompressed, as
    the toolkit's ``binary_mask_to_rle`` writes); either way the counts must be non-negative
    and sum to h * w, the pixel count of the mask. With ``image_hw`` the size must equal the
    image's. A broken RLE is refused here because pycocotools does not check it: a truncated
    string hangs its IoU and a negative count overflows."""
    if not isinstance(rle, Mapping) or "counts" not in rle or "size" not in rle:
        raise ValueError(
            f"{where}: segmentation must be a COCO RLE dict with counts and size (polygons "
            f"are not accepted by BOP), got {_short(rle)}"
        )
    size = rle["size"]
    if (
        not isinstance(size, (list, tuple))
        or len(size) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size)
    ):
        raise ValueError(
            f"{where}: segmentation size must be [height, width] in pixels (two positive "
            f"integers), got {_short(size)}"
        )
    h, w = size
    if h * w > MAX_RLE_PIXELS:
        raise ValueError(f"{where}: segmentation size {h}x{w} is implausibly large")
    if image_hw is not None and (h, w) != tuple(image_hw):
        raise ValueError(
            f"{where}: segmentation size [{h}, {w}] differs from the image size "
            f"[{image_hw[0]}, {image_hw[1]}] (size is [height, width] of the whole image)"
        )
    counts = rle["counts"]
    if isinstance(counts, bytes):
        counts = counts.decode("latin-1")
    if isinstance(counts, str):
        dec = _string_rle_counts(counts)
        if dec is None:
            raise ValueError(
                f"{where}: segmentation counts {_short(counts)} is not a valid COCO compressed "
                "RLE string (truncated or corrupted; write it with pycocotools mask.encode)"
            )
        negative, total = bool((dec < 0).any()), int(dec.sum())
    elif isinstance(counts, list):
        if not all(isinstance(v, int) and not isinstance(v, bool) for v in counts):
            raise ValueError(f"{where}: segmentation counts must be integers")
        negative, total = any(v < 0 for v in counts), sum(counts)
    else:
        raise ValueError(
            f"{where}: segmentation counts must be a compressed RLE string or a list of "
            f"integers, got {type(counts).__name__}"
        )
    if negative:
        raise ValueError(f"{where}: segmentation counts must not be negative")
    if total != h * w:
        raise ValueError(
            f"{where}: segmentation counts sum to {total} pixels but the size {h}x{w} has "
            f"{h * w} (a truncated RLE, or counts for another image size)"
        )
    return h, w


def rle_to_mask(rle: Mapping) -> np.ndarray:
    """Decode a COCO RLE (compressed string or uncompressed list counts) to [H, W] bool."""
    from pycocotools import mask as mask_utils

    h, w = validate_rle(rle, "rle_to_mask")
    counts = rle["counts"]
    if isinstance(counts, list):
        obj = mask_utils.frPyObjects({"counts": counts, "size": [h, w]}, h, w)
    else:
        obj = {
            "counts": counts.encode("ascii") if isinstance(counts, str) else counts,
            "size": [h, w],
        }
    return mask_utils.decode(obj).astype(bool)


def write_detection_results(path, detections: Iterable[Detection2D]) -> None:
    """Write a BOP 2D results JSON (list of COCO results with scene_id, atomic)."""
    rows = []
    for d in detections:
        row = {
            "scene_id": int(d.scene_id),
            "image_id": int(d.im_id),
            "category_id": int(d.obj_id),
            "score": float(d.score),
            "time": float(d.time),
        }
        if d.bbox is not None:
            x, y, w, h = (float(v) for v in d.bbox)
            if w < 0 or h < 0:
                raise ValueError(
                    f"detection scene {d.scene_id} im {d.im_id}: bbox {d.bbox} "
                    "has negative size; BOP boxes are [x, y, width, height]"
                )
            row["bbox"] = [x, y, w, h]
        if d.segmentation is not None:
            validate_rle(d.segmentation, f"detection scene {d.scene_id} im {d.im_id}")
            seg = dict(d.segmentation)
            if isinstance(seg.get("counts"), bytes):
                seg["counts"] = seg["counts"].decode("ascii")
            row["segmentation"] = seg
        rows.append(row)
    write_json_atomic(path, rows)


def _json_number(value, what: str, where: str) -> float:
    """A finite JSON number (int or float, not a bool) as float."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{where}: {what} must be a number, got {_short(value)}")
    try:
        f = float(value)
    except OverflowError:
        f = math.inf
    return _finite(f, what, where)


def read_detection_results(path) -> list[Detection2D]:
    """Read a BOP 2D results JSON (`inout.check_coco_results` keys), validating it.

    Each entry needs integer ``scene_id``, ``image_id``, ``category_id``, a finite numeric
    ``score`` and optionally a finite ``time``; ``bbox`` is [x, y, w, h] with finite values
    and w, h >= 0; ``segmentation`` a COCO RLE (see `validate_rle`). An empty ``bbox`` or
    ``segmentation`` counts as absent (the toolkit writes ``[]`` and ``{}``). Every problem
    raises ValueError naming the file and the entry."""
    path = pathlib.Path(path)
    raw = _load_json(path, "2D results file")
    if not isinstance(raw, list):
        raise ValueError(
            f"{path}: a 2D results file must be a JSON list of detections, got a JSON "
            f"{type(raw).__name__}"
        )
    out = []
    for i, r in enumerate(raw):
        where = f"{path} entry {i}"
        if not isinstance(r, dict):
            raise ValueError(f"{where}: a detection must be a JSON object, got {_short(r)}")
        for key in ("scene_id", "image_id", "category_id", "score"):
            if key not in r:
                raise ValueError(
                    f"{where}: missing {key!r} (BOP 2D results need scene_id, "
                    "image_id, category_id, score, bbox and/or segmentation)"
                )
        for key in ("scene_id", "image_id", "category_id"):
            if not isinstance(r[key], int) or isinstance(r[key], bool):
                raise ValueError(f"{where}: {key} must be an integer, got {_short(r[key])}")
        where = f"{where} (scene {r['scene_id']}, image {r['image_id']})"
        score = _json_number(r["score"], "score", where)
        time = _json_number(r.get("time", -1.0), "time (s, -1 when unknown)", where)
        bbox = r.get("bbox") or None
        if bbox is not None:
            if not isinstance(bbox, list) or len(bbox) != 4:
                raise ValueError(f"{where}: bbox must be [x, y, w, h], got {_short(bbox)}")
            bbox = tuple(_json_number(v, "bbox", where) for v in bbox)
            if bbox[2] < 0 or bbox[3] < 0:
                raise ValueError(
                    f"{where}: bbox {list(bbox)} has negative size; BOP boxes are [x, y, "
                    "width, height], not [x0, y0, x1, y1]"
                )
        seg = r.get("segmentation") or None
        if seg is not None:
            validate_rle(seg, where)
        out.append(
            Detection2D(r["scene_id"], r["image_id"], r["category_id"], score, bbox, seg, time)
        )
    return out
