"""BOP object models: ``models_info.json`` in and out, and model info from vertices."""

from __future__ import annotations

import pathlib
from collections.abc import Iterable, Mapping

import numpy as np

from threept_jax.data.bop.json_format import (
    _int_keys,
    _json_int,
    _load_json,
    entry_errors,
    write_json_atomic,
)
from threept_jax.data.bop.types import MultiviewTarget, ObjectModel, Target
from threept_jax.geometry.diameter import MIN_DIAMETER_MM, mesh_diameter
from threept_jax.geometry.symmetry import Symmetries


def compute_model_info(
    vertices: np.ndarray, symmetries: Symmetries | None = None, obj_id: int = 0, path=None
) -> ObjectModel:
    """Model info from vertices [N, 3] (mm): exact diameter (max pairwise vertex distance,
    `misc.calc_pts_diameter`) and 3D box, as `scripts/calc_model_info.py` computes them."""
    v = np.asarray(vertices, np.float64)
    lo, hi = v.min(0), v.max(0)
    diameter = mesh_diameter(v)
    return ObjectModel(
        int(obj_id),
        diameter,
        lo,
        hi - lo,
        symmetries or Symmetries(),
        None if path is None else pathlib.Path(path),
    )


def _parse_model_info(obj_id: int, info: Mapping, path: pathlib.Path, folder: pathlib.Path):
    where = f"{path} object {obj_id}"
    if "diameter" not in info:
        raise ValueError(
            f"{where}: no 'diameter'; recompute models_info.json "
            "(bop_toolkit scripts/calc_model_info.py)"
        )
    diameter = float(info["diameter"])
    if not diameter >= MIN_DIAMETER_MM:
        raise ValueError(
            f"{where}: diameter {diameter} looks like metres; BOP models and poses are in mm "
            "(scale the PLY and models_info.json by 1000)"
        )
    lo = [float(info.get(k, 0.0)) for k in ("min_x", "min_y", "min_z")]
    size = [float(info.get(k, 0.0)) for k in ("size_x", "size_y", "size_z")]
    mesh = folder / f"obj_{obj_id:06d}.ply"
    return ObjectModel(
        obj_id,
        diameter,
        lo,
        size,
        Symmetries.from_json(info, where),
        mesh if mesh.is_file() else None,
    )


def load_models_info(path) -> dict[int, ObjectModel]:
    """Parse a ``models_info.json`` into {obj_id: ObjectModel} (mesh paths beside it)."""
    path = pathlib.Path(path)
    raw = _int_keys(_load_json(path), path)
    out = {}
    for k, v in sorted(raw.items()):
        with entry_errors(f"{path} object {k}", MODEL_INFO_FORM):
            out[k] = _parse_model_info(k, v, path, path.parent)
    return out


def load_models(models_dir) -> dict[int, ObjectModel]:
    """Load a BOP models folder (``models_info.json`` + ``obj_*.ply``) lazily (no mesh read)."""
    models_dir = pathlib.Path(models_dir)
    info = models_dir / "models_info.json"
    if not info.is_file():
        raise FileNotFoundError(
            f"{models_dir} has no models_info.json; a BOP models folder needs one "
            "(compute it with threept_jax.data.bop.compute_model_info and write_models_info)"
        )
    return load_models_info(info)


def write_models_info(path, models: Mapping[int, ObjectModel] | Iterable[ObjectModel]) -> None:
    """Write ``models_info.json`` for the given models (atomic)."""
    if isinstance(models, Mapping):
        models = models.values()
    write_json_atomic(path, {int(m.obj_id): m.to_json() for m in models})


MODEL_INFO_FORM = ("{diameter: mm, min_x, min_y, min_z, size_x, size_y, size_z: mm[, "
                   "symmetries_discrete, symmetries_continuous]}")
TARGET_FORM = "{scene_id: int, im_id: int[, obj_id: int, inst_count: int]}"
MULTIVIEW_FORM = "{scene_id: int, im_id or im_ids: an int or a list of ints}"


# ----------------------------------------------------------------------------- targets
def load_targets(path) -> list[Target]:
    """Load ``test_targets_bop19.json`` (with obj_id, inst_count) or ``_bop24.json`` (images)."""
    path = pathlib.Path(path)
    raw = _load_json(path)
    if not isinstance(raw, list):
        raise ValueError(
            f"{path}: a targets file must hold a JSON list of "
            "{scene_id, im_id[, obj_id, inst_count]} entries"
        )
    out = []
    for i, t in enumerate(raw):
        with entry_errors(f"{path} entry {i}", TARGET_FORM):
            out.append(_parse_target(t, f"{path} entry {i}"))
    return out


def _parse_target(t, where: str) -> Target:
    if "scene_id" not in t or "im_id" not in t:
        raise ValueError(f"{where} lacks scene_id or im_id: {t}")
    if isinstance(t["im_id"], list):
        raise ValueError(
            f"{where} lists several images; this is a multi-view targets file (read it with "
            "load_multiview_targets); per-image evaluation needs test_targets_bop24.json or "
            "_bop19.json"
        )
    return Target(
        _json_int(t["scene_id"]),
        _json_int(t["im_id"]),
        None if t.get("obj_id") is None else _json_int(t["obj_id"]),
        None if t.get("inst_count") is None else _json_int(t["inst_count"]),
    )


def write_targets(path, targets: Iterable[Target]) -> None:
    """Write a targets file (bop19 style when obj_id is set, else bop24 style)."""
    rows = []
    for t in targets:
        row = {"im_id": int(t.im_id), "scene_id": int(t.scene_id)}
        if t.obj_id is not None:
            row["obj_id"] = int(t.obj_id)
            row["inst_count"] = int(t.inst_count or 1)
        rows.append(row)
    write_json_atomic(path, rows)


#: The multi-view targets file at a dataset's root (BOP 2025).
MULTIVIEW_TARGETS_FILE = "test_targets_multiview_bop25.json"


def write_multiview_targets(path, targets: Iterable[MultiviewTarget]) -> None:
    """Write ``test_targets_multiview_bop25.json``: one ``{"scene_id", "im_ids"}`` group per
    target, a view as its im_id, or as ``[sensor, im_id]`` when it names a sensor (the forms
    :func:`load_multiview_targets` reads)."""
    rows = [{"scene_id": int(t.scene_id),
             "im_ids": [int(i) if sensor is None else [str(sensor), int(i)]
                        for sensor, i in t.views]}
            for t in targets]
    write_json_atomic(path, rows)


def load_multiview_targets(path) -> list[MultiviewTarget]:
    """Load ``test_targets_multiview_bop25.json``: a list of groups with ``scene_id`` and the
    group's views under ``im_id`` (or ``im_ids``): an int, a list of ints, or a list of
    ``[sensor, im_id]`` pairs. Returns one MultiviewTarget per group."""
    path = pathlib.Path(path)
    raw = _load_json(path)
    if not isinstance(raw, list):
        raise ValueError(f"{path}: expected a JSON list of multi-view groups")
    out = []
    for i, g in enumerate(raw):
        with entry_errors(f"{path} group {i}", MULTIVIEW_FORM):
            out.append(_parse_multiview_group(g, f"{path} group {i}"))
    return out


def _parse_multiview_group(g, where: str) -> MultiviewTarget:
    views = g.get("im_ids", g.get("im_id"))
    if "scene_id" not in g or views is None:
        raise ValueError(f"{where} needs scene_id and im_id/im_ids: {g}")
    if not isinstance(views, list):
        views = [views]
    parsed = []
    for v in views:
        if isinstance(v, (list, tuple)) and len(v) == 2:
            parsed.append((str(v[0]), _json_int(v[1])))
        elif isinstance(v, Mapping):
            parsed.append((v.get("sensor"), _json_int(v["im_id"])))
        else:
            parsed.append((None, _json_int(v)))
    return MultiviewTarget(_json_int(g["scene_id"]), tuple(parsed))


#: The robot cell of a synthetic cell dataset (``datagen --layout cell``), at the dataset root:
#: its camera, working distance and ``depth_range_mm`` (zmin, zmax), the depth range detection
#: assumes by default (``python -m infer bop``, ``train.adapt``). Not part of BOP.
CELL_FILE = "cell.json"


def write_cell(root, cell: Mapping) -> None:
    """Write ``cell.json`` into the dataset folder ``root`` (atomic)."""
    write_json_atomic(pathlib.Path(root) / CELL_FILE, dict(cell))


def load_cell(root) -> dict | None:
    """The ``cell.json`` of the dataset folder ``root``, or None when it has none; raises
    ValueError naming the file when its ``depth_range_mm`` is not (zmin, zmax) with
    0 < zmin <= zmax."""
    path = pathlib.Path(root) / CELL_FILE
    if not path.is_file():
        return None
    raw = _load_json(path, "cell file")
    z = raw.get("depth_range_mm") if isinstance(raw, Mapping) else None
    ok = (isinstance(z, list) and len(z) == 2 and all(isinstance(v, (int, float)) for v in z)
          and 0 < z[0] <= z[1])
    if not ok:
        raise ValueError(f"{path}: depth_range_mm must be [zmin, zmax] in mm with 0 < zmin <= "
                         f"zmax, got {z!r}; regenerate the dataset (python -m datagen.generate "
                         "--layout cell) or delete the file to run without a depth range")
    return dict(raw)
