"""The mesh pool of the data generator: CAD meshes from folders and procedural parts, with ids.

3PT is trained on renders of ~110k meshes (docs/design.md section 1). The pool gathers them from

* BOP ``models/`` folders (``obj_XXXXXX.ply`` + ``models_info.json``, whose diameters and
  symmetries are kept: 3PT's losses are symmetry-aware),
* plain trees of OBJ / PLY / GLB / glTF / STL / OFF files (searched recursively),
* in-memory procedural parts (``datagen.procedural``),

and gives every mesh a pool-wide ``obj_id`` (1, 2, ... in a deterministic order: sources in
the order given, BOP objects by id, files by relative path, then procedural parts). The
original dataset id is kept in ``source_obj_id``.

Scanning reads no mesh; meshes are loaded on demand by ``MeshPool.load``. A mesh that cannot be
used (unreadable or corrupt file, no triangles, non-finite vertices, a size that says the units
are wrong) is skipped with a ``MeshSkippedWarning`` naming the file and the reason, and
counted in ``MeshPool.skipped``; it never aborts a run.

Units are millimetres everywhere (BOP). A folder in other units must say so
(``MeshFolder(path, units="m")``); the pool never rescales silently, and a mesh whose diameter
is below ``min_diameter`` mm (default 1, so almost surely metres) is skipped with a message
that names the fix.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import pathlib
import re
import warnings
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
import trimesh

from datagen.procedural import Part
from threept_jax.geometry.diameter import MeshUnitsError, check_units, mesh_diameter
from threept_jax.geometry.symmetry import Symmetries
from threept_jax.geometry.validate import validate_mesh_arrays
from threept_jax.render.mesh import read_trimesh

MESH_EXTENSIONS = (".ply", ".obj", ".glb", ".gltf", ".stl", ".off")
UNITS_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
_BOP_NAME = re.compile(r"^obj_(\d+)\.ply$")


class MeshSkippedWarning(UserWarning):
    """A mesh was skipped (corrupt, empty, wrong units); the message names the file and why."""


@dataclasses.dataclass(frozen=True)
class MeshFolder:
    """A folder of meshes and how to read it.

    Attributes:
      path: a BOP ``models`` folder (it holds ``models_info.json``) or any tree of mesh files.
      units: units of the files' coordinates, one of ``UNITS_TO_MM``; converted to mm on load.
      recenter: move plain meshes' bounding-box centre to the origin, as BOP models are
        (BOP folders are never moved: their poses and ``models_info`` refer to the file frame).
    """

    path: str | pathlib.Path
    units: str = "mm"
    recenter: bool = True


@dataclasses.dataclass(frozen=True, eq=False)
class MeshRecord:
    """One mesh of the pool (lightweight: no geometry unless in memory).

    Attributes:
      obj_id: pool-wide object id (1-based), used in the generated BOP datasets.
      name: readable unique name, e.g. ``"itodd/obj_000001"`` or ``"procedural/gear_0003"``.
      path: the file, or None for an in-memory mesh.
      mesh: the in-memory mesh (mm), or None for a file.
      diameter: mm, from ``models_info.json`` or the procedural part; None until loaded.
      symmetries: the object's symmetries (mm).
      source: the folder or "procedural".
      source_obj_id: the id in the source BOP dataset, else None.
      scale: factor from file units to mm.
      recenter: whether loading moves the bounding-box centre to the origin.
    """

    obj_id: int
    name: str
    path: pathlib.Path | None
    mesh: trimesh.Trimesh | None
    diameter: float | None
    symmetries: Symmetries = dataclasses.field(default_factory=Symmetries)
    source: str = ""
    source_obj_id: int | None = None
    scale: float = 1.0
    recenter: bool = False


@dataclasses.dataclass(frozen=True, eq=False)
class LoadedMesh:
    """A record with its geometry: ``mesh`` in mm (object frame of the pool's BOP output).

    The mesh is shared with the pool's cache (and with the procedural part): treat it as
    read-only and ``copy()`` it before transforming it.
    """

    record: MeshRecord
    mesh: trimesh.Trimesh
    diameter: float

    def models_info(self) -> dict[str, Any]:
        """The BOP ``models_info.json`` entry of this mesh (mm)."""
        lo, hi = self.mesh.bounds
        info: dict[str, Any] = {"diameter": float(self.diameter)}
        for k, axis in enumerate("xyz"):
            info[f"min_{axis}"] = float(lo[k])
            info[f"max_{axis}"] = float(hi[k])
            info[f"size_{axis}"] = float(hi[k] - lo[k])
        info.update(self.record.symmetries.to_json())
        return info


def load_mesh_file(path: str | pathlib.Path) -> trimesh.Trimesh:
    """Read one mesh file as a single triangle mesh in file units (the pool's only reader).

    Multi-part files (GLB scenes, OBJ groups) are merged with their node transforms. A file
    that cannot be read, is empty, has NaN/inf vertices, face indices out of range or more
    than ``MAX_MESH_FACES`` faces raises ValueError naming the file and the problem.
    """
    return read_trimesh(path)


def _read_models_info(path: pathlib.Path) -> dict[int, dict[str, Any]]:
    try:
        raw = json.loads(path.read_text())
        return {int(k): v for k, v in raw.items()}
    except Exception as e:
        raise ValueError(
            f"cannot read {path}: {e}; it must map object ids to BOP model info"
        ) from e


def _scan_folder(folder: MeshFolder) -> list[dict[str, Any]]:
    """Entries (record fields without obj_id) for one folder, in deterministic order."""
    root = pathlib.Path(folder.path).expanduser()
    if not root.is_dir():
        raise ValueError(f"mesh folder {root} does not exist or is not a directory")
    if folder.units not in UNITS_TO_MM:
        raise ValueError(
            f"unknown units {folder.units!r} for {root}; use one of {sorted(UNITS_TO_MM)}"
        )
    scale = UNITS_TO_MM[folder.units]
    label = root.parent.name if root.name == "models" else root.name
    info_path = root / "models_info.json"
    entries = []
    if info_path.is_file():
        info = _read_models_info(info_path)
        files = {}
        for p in root.iterdir():
            m = _BOP_NAME.match(p.name)
            if m:
                files[int(m.group(1))] = p
        for oid in sorted(files):
            meta = info.get(oid, {})
            diameter = meta.get("diameter")
            entries.append(
                dict(
                    name=f"{label}/obj_{oid:06d}",
                    path=files[oid],
                    mesh=None,
                    diameter=float(diameter) * scale if diameter is not None else None,
                    symmetries=Symmetries.from_json(meta, f"{root} obj {oid}").scaled(scale),
                    source=str(root),
                    source_obj_id=oid,
                    scale=scale,
                    recenter=False,
                )
            )
        return entries
    paths = sorted(
        (p for p in root.rglob("*") if p.is_file() and p.suffix.lower() in MESH_EXTENSIONS),
        key=lambda p: p.relative_to(root).as_posix(),
    )
    for p in paths:
        rel = p.relative_to(root).with_suffix("").as_posix()
        entries.append(
            dict(
                name=f"{label}/{rel}",
                path=p,
                mesh=None,
                diameter=None,
                source=str(root),
                source_obj_id=None,
                scale=scale,
                recenter=folder.recenter,
            )
        )
    return entries


class MeshPool:
    """An ordered set of ``MeshRecord`` with on-demand, skip-on-error loading.

    ``load(i)`` returns a ``LoadedMesh`` or None (the mesh was skipped: a ``MeshSkippedWarning``
    was issued once and ``skipped`` counts it). Loaded meshes are kept in a small LRU cache.
    """

    def __init__(
        self,
        records: Sequence[MeshRecord],
        *,
        min_diameter: float = 1.0,
        max_diameter: float = 5000.0,
        cache_size: int = 256,
        units_option: str = "MeshFolder(path, units='{}')",
    ):
        ids = [r.obj_id for r in records]
        if len(set(ids)) != len(ids):
            raise ValueError("obj_id values in a MeshPool must be unique")
        self.records: tuple[MeshRecord, ...] = tuple(records)
        self.min_diameter = min_diameter
        self.max_diameter = max_diameter
        # How a wrong-units message names the fix ("{}" is a unit): the CLI passes its flag.
        self.units_option = units_option
        self._cache: collections.OrderedDict[int, LoadedMesh] = collections.OrderedDict()
        self._cache_size = cache_size
        self._bad: dict[int, str] = {}

    def __len__(self) -> int:
        return len(self.records)

    @property
    def skipped(self) -> int:
        """Number of meshes skipped so far (each counted once)."""
        return len(self._bad)

    @property
    def skipped_reasons(self) -> dict[str, str]:
        """{mesh name: reason} of the skipped meshes."""
        return {self.records[i].name: why for i, why in self._bad.items()}

    def load(self, index: int) -> LoadedMesh | None:
        """The mesh at ``index`` (0-based position in ``records``), or None if it is unusable."""
        if index in self._bad:
            return None
        if index in self._cache:
            self._cache.move_to_end(index)
            return self._cache[index]
        rec = self.records[index]
        try:
            if rec.mesh is not None:
                mesh = rec.mesh
                validate_mesh_arrays(np.asarray(mesh.vertices), np.asarray(mesh.faces), rec.name)
            else:
                mesh = load_mesh_file(rec.path)
                if rec.scale != 1.0:
                    mesh.apply_scale(rec.scale)
                if rec.recenter:
                    mesh.apply_translation(-mesh.bounds.mean(0))
            diameter = check_units(
                mesh_diameter(np.asarray(mesh.vertices)),
                rec.path if rec.path is not None else rec.name,
                self.min_diameter,
                self.max_diameter,
            )
        except Exception as e:  # a bad mesh is skipped, never fatal
            where = rec.path if rec.path is not None else rec.name
            if isinstance(e, MeshUnitsError):
                reason = e.message(self.units_option)
            elif isinstance(e, ValueError):
                reason = str(e)
            else:
                reason = f"{type(e).__name__}: {e}"
            self._bad[index] = reason
            said = reason if reason.startswith(str(where)) else f"{where}: {reason}"
            warnings.warn(f"skipping mesh {said}", MeshSkippedWarning, stacklevel=2)
            return None
        if rec.diameter is not None and abs(diameter - rec.diameter) > 0.05 * rec.diameter:
            warnings.warn(
                f"mesh {rec.path}: diameter {diameter:.2f} mm differs from models_info.json "
                f"({rec.diameter:.2f} mm); check the folder's units",
                UserWarning,
                stacklevel=2,
            )
        loaded = LoadedMesh(rec, mesh, diameter)
        self._cache[index] = loaded
        if len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return loaded

    def load_all(self, indices: Iterable[int] | None = None) -> list[LoadedMesh]:
        """Load ``indices`` (default: all); skipped meshes are left out of the result."""
        idx = range(len(self)) if indices is None else indices
        return [m for m in (self.load(i) for i in idx) if m is not None]

    def sample(self, rng: np.random.Generator, n: int, max_redraws: int = 100) -> list[int]:
        """``n`` distinct usable indices drawn uniformly (fewer if the pool has fewer).

        Unusable meshes met on the way are skipped (warned and counted) and replaced by new
        draws, so the result depends only on the generator state and the pool's files. The
        search gives up after ``max_redraws + n`` unusable meshes.
        """
        order = rng.permutation(len(self))
        out = []
        misses = 0
        for i in order:
            if len(out) == n or misses > max_redraws + n:
                break
            if self.load(int(i)) is None:
                misses += 1
                continue
            out.append(int(i))
        return out


def build_pool(
    folders: Sequence[str | pathlib.Path | MeshFolder] = (),
    parts: Sequence[Part] = (),
    *,
    first_obj_id: int = 1,
    **pool_kwargs,
) -> MeshPool:
    """Scan ``folders`` (paths or ``MeshFolder``) and add procedural ``parts``; ids in that order.

    Raises ValueError when a folder is missing or nothing was found (a configuration error,
    unlike a bad mesh, which is skipped at load time).
    """
    entries = []
    for f in folders:
        folder = f if isinstance(f, MeshFolder) else MeshFolder(f)
        found = _scan_folder(folder)
        if not found:
            warnings.warn(
                f"no meshes ({', '.join(MESH_EXTENSIONS)}) under {folder.path}",
                UserWarning,
                stacklevel=2,
            )
        entries += found
    counts: dict[str, int] = collections.Counter()
    for part in parts:
        k = counts[part.family]
        counts[part.family] += 1
        entries.append(
            dict(
                name=f"procedural/{part.family}_{k:04d}",
                path=None,
                mesh=part.mesh,
                diameter=part.diameter,
                symmetries=part.symmetries,
                source="procedural",
            )
        )
    if not entries:
        raise ValueError(
            f"no meshes found in {[str(f) for f in folders]} and no procedural parts given; "
            f"point to BOP models folders or trees of {', '.join(MESH_EXTENSIONS)} files"
        )
    records = [MeshRecord(obj_id=first_obj_id + k, **e) for k, e in enumerate(entries)]
    return MeshPool(records, **pool_kwargs)
