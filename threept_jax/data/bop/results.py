"""BOP result files: the 6D CSV and the 2D COCO JSON with RLE masks."""

from __future__ import annotations

import pathlib
from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from threept_jax.data.bop.json_format import _load_json, write_json_atomic
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


def read_pose_results(path, rotation_atol: float = 1e-3) -> list[PoseEstimate]:
    """Read a BOP 6D results CSV (`inout.load_bop_results`, version bop19), validating it."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"results file {path} does not exist")
    out = []
    with open(path) as f:
        for line_no, line in enumerate(f, start=1):
            if line_no == 1 and POSE_CSV_HEADER in line:
                continue
            if not line.strip():
                continue
            elems = line.rstrip("\r\n").split(",")
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
                raise ValueError(f"{where}: could not parse the row ({e})") from None
            if t.shape != (3,):
                raise ValueError(f"{where}: t must have 3 values (mm), got {t.size}")
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


def rle_to_mask(rle: Mapping) -> np.ndarray:
    """Decode a COCO RLE (compressed string or uncompressed list counts) to [H, W] bool."""
    from pycocotools import mask as mask_utils

    h, w = (int(v) for v in rle["size"])
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
            seg = dict(d.segmentation)
            if isinstance(seg.get("counts"), bytes):
                seg["counts"] = seg["counts"].decode("ascii")
            row["segmentation"] = seg
        rows.append(row)
    write_json_atomic(path, rows)


def read_detection_results(path) -> list[Detection2D]:
    """Read a BOP 2D results JSON (`inout.check_coco_results` keys), validating it."""
    path = pathlib.Path(path)
    raw = _load_json(path)
    if not isinstance(raw, list):
        raise ValueError(f"{path}: a 2D results file must be a JSON list of detections")
    out = []
    for i, r in enumerate(raw):
        where = f"{path} entry {i}"
        for key in ("scene_id", "image_id", "category_id", "score"):
            if key not in r:
                raise ValueError(
                    f"{where}: missing {key!r} (BOP 2D results need scene_id, "
                    "image_id, category_id, score, bbox and/or segmentation)"
                )
        for key in ("scene_id", "image_id", "category_id"):
            if not isinstance(r[key], int) or isinstance(r[key], bool):
                raise ValueError(f"{where}: {key} must be an integer, got {r[key]!r}")
        bbox = r.get("bbox") or None
        if bbox is not None and len(bbox) != 4:
            raise ValueError(f"{where}: bbox must be [x, y, w, h], got {bbox}")
        seg = r.get("segmentation") or None
        if seg is not None and (
            not isinstance(seg, Mapping) or "counts" not in seg or "size" not in seg
        ):
            raise ValueError(
                f"{where}: segmentation must be a COCO RLE dict with counts and "
                "size (polygons are not accepted by BOP)"
            )
        out.append(
            Detection2D(
                r["scene_id"],
                r["image_id"],
                r["category_id"],
                float(r["score"]),
                None if bbox is None else tuple(float(v) for v in bbox),
                seg,
                float(r.get("time", -1.0)),
            )
        )
    return out
