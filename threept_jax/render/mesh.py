"""CAD meshes: loading, unit checks, preparation for the rasterizer, padding to size buckets.

A :class:`Mesh` is a frozen, host-side (NumPy) triangle mesh in millimetres (docs/design.md
section 3): vertices, faces, unit vertex normals, and optionally vertex colours or UV
coordinates with a texture image, plus the BOP symmetries when ``models_info.json`` provides
them.

Preparation for the JAX rasterizer (docs/design.md section 4) bounds the work per triangle:

* :func:`decimate` reduces the face count to a budget (quadric edge collapse, fast-simplification)
  and carries colours and UVs over to the simplified surface;
* :func:`subdivide` splits edges until none is longer than a bound (conforming red-green split:
  no T-junctions, so no cracks);
* :func:`prepare_mesh` does both, with the edge bound given as a fraction of the diameter;
* :func:`to_raster_mesh` turns a mesh into per-face tables padded to a size bucket, so that
  meshes of similar size share one compiled renderer (vertices never reach compiled code).
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import re
import warnings
from typing import Any

import numpy as np

from threept_jax.data.ply import check_ply_counts
from threept_jax.geometry.diameter import check_units, mesh_diameter
from threept_jax.geometry.symmetry import Symmetries
from threept_jax.geometry.validate import validate_mesh_arrays

_UNIT_SCALE = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
DEFAULT_GREY = 0.7  # albedo of meshes without colours or texture
#: Largest face count :func:`load_mesh` accepts: loading needs about 0.5 kB per face (a 2M-face
#: mesh peaks near 1 GB), so this bounds it near 5 GB instead of failing late, out of memory.
MAX_MESH_FACES = 10_000_000


def read_trimesh(path: str | pathlib.Path, **kwargs):
    """Read one mesh file with trimesh (no processing) as a single ``trimesh.Trimesh``, checked.

    The one reader of mesh files for :func:`load_mesh` and the datagen mesh pool: a file that
    cannot be read, holds no triangles, has NaN/inf vertices, face indices out of range, fewer
    elements than its PLY header declares (trimesh returns a partial mesh), or more than
    ``MAX_MESH_FACES`` faces raises ValueError naming the file, before any processing.
    """
    import logging

    import trimesh

    # trimesh logs a whole traceback for a texture named in a PLY but missing beside it;
    # load_mesh says so in one warning line instead.
    trimesh_log = logging.getLogger("trimesh")
    level = trimesh_log.level
    trimesh_log.setLevel(logging.CRITICAL)
    try:
        tm = trimesh.load(str(path), process=False, force="mesh", **kwargs)
        if not isinstance(tm, trimesh.Trimesh):
            raise ValueError(f"no triangle mesh in it (got {type(tm).__name__})")
        vertices = np.asarray(tm.vertices, np.float64).reshape(-1, 3)
        faces = np.asarray(tm.faces, np.int64).reshape(-1, 3)
    except Exception as e:  # trimesh and numpy raise anything on corrupt files
        raise ValueError(
            f"{path}: cannot read the mesh ({type(e).__name__}: {e}); the file is corrupt, "
            "truncated or not a mesh"
        ) from None
    finally:
        trimesh_log.setLevel(level)
    if str(path).lower().endswith(".ply"):
        check_ply_counts(path, len(vertices), len(faces))
    validate_mesh_arrays(vertices, faces, path)
    if len(faces) > MAX_MESH_FACES:
        raise ValueError(
            f"{path}: {len(faces)} faces, above the {MAX_MESH_FACES} that a mesh may have "
            f"(about {len(faces) * 5e-7:.0f} GB to load); decimate the file first, e.g. with "
            "fast_simplification.simplify (the decimation of prepare_mesh(max_faces=)) or "
            "MeshLab's quadric edge collapse"
        )
    return tm


def _readonly(a: np.ndarray | None) -> np.ndarray | None:
    if a is not None:
        a.setflags(write=False)
    return a


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals [N, 3], shared by vertices at the same position.

    Vertices duplicated along UV seams get the normal of the welded surface, so shading shows
    no seam.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    _, weld = np.unique(v, axis=0, return_inverse=True)
    weld = weld.reshape(-1)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # length = 2 * area
    acc = np.zeros((weld.max() + 1, 3))
    for k in range(3):
        np.add.at(acc, weld[f[:, k]], fn)
    n = acc[weld]
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    fallback = np.array([0.0, 0.0, 1.0])
    return np.where(norm > 0, n / np.maximum(norm, 1e-30), fallback).astype(np.float32)


@dataclasses.dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh in millimetres (host arrays, read-only).

    Attributes:
      vertices: [N, 3] float32, mm, object frame.
      faces: [F, 3] int32 vertex indices, counter-clockwise seen from outside.
      normals: [N, 3] float32 unit vertex normals (object frame).
      colors: [N, 3] float32 vertex colours in [0, 1], or None.
      uv: [N, 2] float32 texture coordinates (OpenGL convention: v = 0 is the image's bottom
        row), or None.
      texture: [Ht, Wt, 3] uint8 RGB image (row 0 at the top), or None; present iff ``uv`` is.
      symmetries: the object's symmetries (BOP ``models_info.json`` beside the file).
      name: a label for messages.
      diameter: largest vertex distance in mm (computed when not given).
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    uv: np.ndarray | None = None
    texture: np.ndarray | None = None
    symmetries: Symmetries = dataclasses.field(default_factory=Symmetries)
    name: str = "mesh"
    diameter: float | None = None

    def __post_init__(self):
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731  (frozen dataclass)
        v = np.ascontiguousarray(self.vertices, dtype=np.float32)
        f = np.ascontiguousarray(self.faces)
        if v.ndim != 2 or v.shape[-1] != 3:
            raise ValueError(f"mesh {self.name!r}: vertices must be [N, 3], got {v.shape}")
        if f.ndim != 2 or f.shape[-1] != 3:
            raise ValueError(f"mesh {self.name!r}: faces must be [F, 3] triangles, got {f.shape}")
        validate_mesh_arrays(v, f, f"mesh {self.name!r}")
        f = f.astype(np.int32)
        set_("vertices", _readonly(v))
        set_("faces", _readonly(f))
        n = vertex_normals(v, f) if self.normals is None else np.asarray(self.normals, np.float32)
        if n.shape != v.shape:
            raise ValueError(f"mesh {self.name!r}: normals must be {v.shape}, got {n.shape}")
        norm = np.linalg.norm(n, axis=-1, keepdims=True)
        # Some BOP files store unnormalised normals (YCB-V obj 10); zero normals fall back to the
        # welded face normals.
        if (norm <= 1e-12).any():
            n = np.where(norm > 1e-12, n / np.maximum(norm, 1e-12), vertex_normals(v, f))
        else:
            n = n / norm
        set_("normals", _readonly(np.ascontiguousarray(n, np.float32)))
        if self.colors is not None:
            c = np.asarray(self.colors, np.float32)
            if c.shape != v.shape:
                raise ValueError(f"mesh {self.name!r}: colors must be {v.shape}, got {c.shape}")
            set_("colors", _readonly(np.clip(c, 0.0, 1.0)))
        if (self.uv is None) != (self.texture is None):
            raise ValueError(f"mesh {self.name!r}: uv and texture must be given together")
        if self.uv is not None:
            uv = np.asarray(self.uv, np.float32)
            if uv.shape != (len(v), 2):
                raise ValueError(f"mesh {self.name!r}: uv must be [{len(v)}, 2], got {uv.shape}")
            tex = np.asarray(self.texture)
            if tex.ndim != 3 or tex.shape[-1] != 3 or tex.dtype != np.uint8:
                raise ValueError(
                    f"mesh {self.name!r}: texture must be [Ht, Wt, 3] uint8 RGB, "
                    f"got {tex.shape} {tex.dtype}"
                )
            set_("uv", _readonly(uv))
            set_("texture", _readonly(np.ascontiguousarray(tex)))
        if self.diameter is None:
            set_("diameter", mesh_diameter(v))
        check_units(float(self.diameter), self.name)

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        """(min [3], max [3]) corners of the axis-aligned bounding box in mm."""
        return self.vertices.min(0), self.vertices.max(0)

    @property
    def center(self) -> np.ndarray:
        """Centre [3] of the bounding box (centre of the bounding sphere used for depth ranges)."""
        lo, hi = self.bbox
        return ((lo.astype(np.float64) + hi) / 2).astype(np.float32)

    @property
    def radius(self) -> float:
        """Radius of the sphere about :attr:`center` holding every vertex, in mm."""
        return float(np.linalg.norm(self.vertices - self.center, axis=-1).max())

    @property
    def max_edge(self) -> float:
        """Longest edge length in mm."""
        e = edge_lengths(self.vertices, self.faces)
        return float(e.max())

    def replace(self, **changes: Any) -> Mesh:
        """A copy with fields replaced (normals are recomputed when geometry changes)."""
        if ("vertices" in changes or "faces" in changes) and "normals" not in changes:
            changes["normals"] = None
        if "vertices" in changes and "diameter" not in changes:
            changes["diameter"] = None
        return dataclasses.replace(self, **changes)


def edge_lengths(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Lengths [F, 3] of edges (v0v1, v1v2, v2v0) of every face."""
    t = np.asarray(vertices, np.float64)[np.asarray(faces)]
    return np.linalg.norm(t - np.roll(t, -1, axis=1), axis=-1)


# --------------------------------------------------------------------------------------------
# Loading


def _ply_texture_name(path: pathlib.Path) -> str | None:
    """The ``comment TextureFile <name>`` of a PLY header, if any."""
    with open(path, "rb") as fh:
        for _ in range(200):
            line = fh.readline()
            if not line or line.strip() == b"end_header":
                break
            m = re.match(rb"comment\s+TextureFile\s+(\S+)", line.strip())
            if m:
                return m.group(1).decode("utf-8", "replace")
    return None


def _bop_models_info(path: pathlib.Path, models_info) -> dict | None:
    if models_info is None:
        return None
    if isinstance(models_info, dict):
        return models_info
    info_path = path.parent / "models_info.json" if models_info == "auto" else models_info
    info_path = pathlib.Path(info_path)
    m = re.match(r"obj_0*(\d+)", path.stem)
    if not info_path.is_file() or not m:
        if models_info != "auto":
            raise FileNotFoundError(f"models_info {info_path} not found or {path.name} not obj_*")
        return None
    with open(info_path) as fh:
        return json.load(fh).get(str(int(m.group(1))))


def load_mesh(
    path: str | pathlib.Path,
    units: str = "mm",
    models_info: str | pathlib.Path | dict | None = "auto",
) -> Mesh:
    """Load a PLY / OBJ / GLB / STL mesh into a :class:`Mesh` in millimetres.

    Args:
      path: mesh file. A PLY's ``comment TextureFile`` image is read from beside it; a missing
        texture file drops the UVs with a warning (YCB-V ships textures for a few objects only).
      units: the file's length unit, one of 'mm', 'cm', 'm', 'in'; vertices are scaled to mm.
        A diameter outside [1, 5000] mm after conversion raises
        :class:`~threept_jax.geometry.diameter.MeshUnitsError`: pick the right ``units``.
      models_info: BOP ``models_info.json`` for symmetries: 'auto' looks beside the file for an
        ``obj_<id>`` entry, a path or an already-parsed entry dict may be given, None skips.

    Non-watertight or degenerate meshes load with a warning. A file that cannot be read, is
    empty, has NaN/inf vertices or face indices out of range, or has more than
    ``MAX_MESH_FACES`` faces raises ValueError naming the file, before any processing.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file {path} not found")
    if units not in _UNIT_SCALE:
        raise ValueError(f"units must be one of {sorted(_UNIT_SCALE)}, got {units!r}")
    is_ply = path.suffix.lower() == ".ply"
    tm = read_trimesh(path, **({"skip_materials": True} if is_ply else {}))
    vertices = np.asarray(tm.vertices, np.float64) * _UNIT_SCALE[units]
    faces = np.asarray(tm.faces, np.int64)

    normals = None
    if "vertex_normals" in tm._cache.cache:  # normals stored in the file, not recomputed
        normals = np.asarray(tm._cache.cache["vertex_normals"], np.float64)
        if normals.shape != vertices.shape:
            normals = None

    colors = uv = texture = None
    visual = tm.visual
    if visual.kind == "texture" and getattr(visual, "uv", None) is not None:
        image = None
        if is_ply:
            tex_name = _ply_texture_name(path)
            if tex_name is not None and (path.parent / tex_name).is_file():
                from PIL import Image

                image = Image.open(path.parent / tex_name)
            elif tex_name is not None:
                warnings.warn(
                    f"{path.name}: texture {tex_name} not found beside the mesh; "
                    "rendering it untextured",
                    stacklevel=2,
                )
        else:
            mat = visual.material
            image = getattr(mat, "image", None) or getattr(mat, "baseColorTexture", None)
        if image is not None:
            texture = np.asarray(image.convert("RGB"), np.uint8)
            uv = np.asarray(visual.uv, np.float32)
    elif visual.kind in ("vertex", "face"):
        colors = np.asarray(visual.vertex_colors, np.float32)[:, :3] / 255.0

    info = _bop_models_info(path, models_info)
    symmetries = Symmetries.from_json(info or {}, f"{path.name} models_info.json")

    vertices, faces, normals, colors, uv, dropped = _remove_duplicate_faces(
        vertices, faces, normals, colors, uv
    )
    if dropped:
        warnings.warn(
            f"{path.name}: dropped {dropped} of {dropped + len(faces)} faces that repeat another "
            "face (same vertex positions and attributes, same winding)",
            stacklevel=2,
        )
    mesh = Mesh(
        vertices=vertices,
        faces=faces,
        normals=normals,
        colors=colors,
        uv=uv,
        texture=texture,
        symmetries=symmetries,
        name=path.name,
        diameter=check_units(mesh_diameter(vertices), path),
    )
    _warn_quality(mesh)
    return mesh


def _remove_duplicate_faces(vertices, faces, normals, colors, uv):
    """Drop faces that repeat an earlier face and the vertices no face uses.

    Vertices are identified by position and every attribute, so UV-seam copies stay apart;
    faces by their vertex cycle (same winding). Returns the arrays and the number dropped.
    """
    cols = [vertices] + [a for a in (normals, colors, uv) if a is not None]
    _, ident = np.unique(np.concatenate(cols, axis=1), axis=0, return_inverse=True)
    f = ident.reshape(-1)[faces]
    # Rotate each cycle to start at its smallest vertex (winding preserved).
    r = np.argmin(f, axis=1)
    f = np.take_along_axis(f, (r[:, None] + np.arange(3)[None]) % 3, axis=1)
    _, first = np.unique(f, axis=0, return_index=True)
    keep = np.sort(first)
    dropped = len(faces) - len(keep)
    if dropped == 0:
        return vertices, faces, normals, colors, uv, 0
    faces = faces[keep]
    used, faces = np.unique(faces, return_inverse=True)
    faces = faces.reshape(-1, 3)
    pick = lambda a: None if a is None else a[used]  # noqa: E731
    return vertices[used], faces, pick(normals), pick(colors), pick(uv), dropped


def _warn_quality(mesh: Mesh) -> None:
    area2 = np.linalg.norm(
        np.cross(
            mesh.vertices[mesh.faces[:, 1]] - mesh.vertices[mesh.faces[:, 0]],
            mesh.vertices[mesh.faces[:, 2]] - mesh.vertices[mesh.faces[:, 0]],
        ),
        axis=-1,
    )
    degenerate = int((area2 <= 1e-12 * mesh.diameter**2).sum())
    if degenerate:
        warnings.warn(
            f"{mesh.name}: {degenerate} of {mesh.num_faces} faces are degenerate (zero area); "
            "they are never rendered",
            stacklevel=3,
        )
    # Welding by position first: seams split for UVs do not make a mesh open.
    import trimesh

    welded = trimesh.Trimesh(mesh.vertices, mesh.faces, process=True, validate=False)
    if not welded.is_watertight:
        warnings.warn(
            f"{mesh.name}: mesh is not watertight; holes show back faces, and back-face culling "
            "is off for it",
            stacklevel=3,
        )


def is_closed(mesh: Mesh) -> bool:
    """Whether the position-welded mesh is watertight with consistent outward winding.

    Back faces of such a mesh are never visible, so a renderer may cull them.
    """
    import trimesh

    welded = trimesh.Trimesh(mesh.vertices, mesh.faces, process=True, validate=False)
    return bool(welded.is_watertight and welded.is_winding_consistent and welded.volume > 0)


# --------------------------------------------------------------------------------------------
# Preparation


def _barycentric(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Barycentric coordinates [M, 3] of points p [M, 3] projected on triangles tri [M, 3, 3]."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1, v2 = b - a, c - a, p - a
    d00 = (v0 * v0).sum(-1)
    d01 = (v0 * v1).sum(-1)
    d11 = (v1 * v1).sum(-1)
    d20 = (v2 * v0).sum(-1)
    d21 = (v2 * v1).sum(-1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) < 1e-30, 1e-30, den)
    w1 = (d11 * d20 - d01 * d21) / den
    w2 = (d00 * d21 - d01 * d20) / den
    return np.stack([1 - w1 - w2, w1, w2], -1)


def decimate(mesh: Mesh, max_faces: int) -> Mesh:
    """Quadric-error decimation (fast-simplification) to at most about ``max_faces`` faces.

    Vertex colours come from the nearest original vertex. UVs are per face corner: each new
    face takes the UV chart of the original face nearest to its centroid and its corners'
    barycentric coordinates there, so texture charts never blend across seams (corners are
    unwelded, positions stay shared, so no cracks). Normals are recomputed.
    """
    import fast_simplification
    from scipy.spatial import cKDTree

    if max_faces < 4:
        raise ValueError(f"max_faces must be >= 4, got {max_faces}")
    if mesh.num_faces <= max_faces:
        return mesh
    # Seams duplicate vertices; simplify the welded surface so seams do not become borders.
    welded, weld = np.unique(mesh.vertices.astype(np.float64), axis=0, return_inverse=True)
    wfaces = weld.reshape(-1)[mesh.faces]
    pts, tris = fast_simplification.simplify(
        welded, wfaces.astype(np.int32), target_count=int(max_faces)
    )
    tris = np.asarray(tris, np.int64)
    keep = (tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 2] != tris[:, 0])
    tris = tris[keep]
    used, tris = np.unique(tris, return_inverse=True)
    tris = tris.reshape(-1, 3)
    pts = np.asarray(pts, np.float64)[used]
    colors = uv = None
    if mesh.colors is not None:
        _, nearest = cKDTree(mesh.vertices).query(pts)
        colors = mesh.colors[nearest]
    if mesh.uv is not None:
        old_tri = mesh.vertices.astype(np.float64)[mesh.faces]
        _, src = cKDTree(old_tri.mean(1)).query(pts[tris].mean(1))
        corners = pts[tris].reshape(-1, 3)
        bary = _barycentric(corners, np.repeat(old_tri[src], 3, axis=0))
        old_uv = mesh.uv[mesh.faces[src]]  # [F', 3, 2]
        uv = np.einsum("mk,mkc->mc", bary, np.repeat(old_uv, 3, axis=0)).astype(np.float32)
        pts = corners
        tris = np.arange(len(corners)).reshape(-1, 3)
    return Mesh(
        vertices=pts,
        faces=tris,
        colors=colors,
        uv=uv,
        texture=mesh.texture,
        symmetries=mesh.symmetries,
        name=mesh.name,
        diameter=mesh.diameter,
    )


def subdivide(mesh: Mesh, max_edge: float, max_iterations: int = 16) -> Mesh:
    """Split edges until none is longer than ``max_edge`` mm (conforming red-green refinement).

    Every marked edge is split at its midpoint; a face with 1, 2 or 3 marked edges becomes 2, 3
    or 4 faces, so neighbours stay conforming (no T-junctions). Vertex attributes (normals,
    colours, UVs) are interpolated linearly at midpoints; edges are keyed by vertex index, so
    seam copies split identically and stay crack-free.
    """
    if max_edge <= 0:
        raise ValueError(f"max_edge must be > 0 mm, got {max_edge}")
    v = mesh.vertices.astype(np.float64)
    f = mesh.faces.astype(np.int64)
    attrs = {k: getattr(mesh, k) for k in ("normals", "colors", "uv")}
    attrs = {k: a.astype(np.float64) for k, a in attrs.items() if a is not None}
    for _ in range(max_iterations):
        length = np.linalg.norm(v[f] - v[np.roll(f, -1, axis=1)], axis=-1)  # [F, 3]
        marked = length > max_edge
        if not marked.any():
            break
        # Unique undirected edges among the marked ones, and the midpoint vertex of each.
        e = np.stack([f, np.roll(f, -1, axis=1)], -1)  # [F, 3, 2], edge k = (f_k, f_k+1)
        ekey = np.sort(e, axis=-1)
        ekey = ekey[..., 0] * (len(v) + 1) + ekey[..., 1]
        # An edge is split if it is marked in any face that holds it.
        split_keys = np.unique(ekey[marked])
        is_split = np.isin(ekey, split_keys)
        mid_of_key = {}
        ends = np.stack([split_keys // (len(v) + 1), split_keys % (len(v) + 1)], -1)
        new_index = len(v) + np.arange(len(split_keys))
        v = np.concatenate([v, v[ends].mean(1)])
        for k, a in attrs.items():
            attrs[k] = np.concatenate([a, a[ends].mean(1)])
        mid_of_key = np.full(ekey.shape, -1, np.int64)
        pos = np.searchsorted(split_keys, ekey)
        mid_of_key[is_split] = new_index[pos[is_split]]
        f = _split_faces(f, is_split, mid_of_key, v)
    if "normals" in attrs:
        n = attrs["normals"]
        attrs["normals"] = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    return Mesh(
        vertices=v,
        faces=f,
        normals=attrs.get("normals"),
        colors=attrs.get("colors"),
        uv=attrs.get("uv"),
        texture=mesh.texture,
        symmetries=mesh.symmetries,
        name=mesh.name,
        diameter=mesh.diameter,
    )


def _split_faces(f: np.ndarray, split: np.ndarray, mid: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Split faces f [F, 3] whose edges (k -> k+1) are marked in split [F, 3].

    mid [F, 3] holds the midpoint vertex of each marked edge; v the vertex positions.
    """
    out = [f[~split.any(1)]]
    count = split.sum(1)
    # Rotate every face so its marked pattern is canonical: one split -> edge 0; two -> edges 0, 1
    # (edge 2 kept); three -> any.
    for n_split in (1, 2, 3):
        sel = np.nonzero(count == n_split)[0]
        if len(sel) == 0:
            continue
        s, ff, mm = split[sel], f[sel], mid[sel]
        if n_split == 1:
            shift = np.argmax(s, axis=1)
        elif n_split == 2:
            shift = (np.argmin(s, axis=1) + 1) % 3  # the unsplit edge becomes edge 2
        else:
            shift = np.zeros(len(sel), np.int64)
        idx = (np.arange(3)[None, :] + shift[:, None]) % 3
        ff = np.take_along_axis(ff, idx, 1)
        mm = np.take_along_axis(mm, idx, 1)
        a, b, c = ff[:, 0], ff[:, 1], ff[:, 2]
        mab, mbc, mca = mm[:, 0], mm[:, 1], mm[:, 2]
        if n_split == 1:
            out += [np.stack([a, mab, c], 1), np.stack([mab, b, c], 1)]
        elif n_split == 2:
            # Triangle (mab, b, mbc) and the quad (a, mab, mbc, c) split on its shorter diagonal.
            out.append(np.stack([mab, b, mbc], 1))
            d1 = np.linalg.norm(v[a] - v[mbc], axis=-1)
            d2 = np.linalg.norm(v[mab] - v[c], axis=-1)
            use1 = (d1 <= d2)[:, None]
            out.append(np.where(use1, np.stack([a, mab, mbc], 1), np.stack([a, mab, c], 1)))
            out.append(np.where(use1, np.stack([a, mbc, c], 1), np.stack([mab, mbc, c], 1)))
        else:
            out += [
                np.stack([a, mab, mca], 1),
                np.stack([mab, b, mbc], 1),
                np.stack([mca, mbc, c], 1),
                np.stack([mab, mbc, mca], 1),
            ]
    return np.concatenate(out)


def resize_texture(texture: np.ndarray, max_size: int) -> np.ndarray:
    """Downsample a texture [Ht, Wt, 3] uint8 so its longer side is at most ``max_size``."""
    h, w = texture.shape[:2]
    if max(h, w) <= max_size:
        return texture
    from PIL import Image

    s = max_size / max(h, w)
    size = (max(1, round(w * s)), max(1, round(h * s)))
    return np.asarray(Image.fromarray(texture).resize(size, Image.Resampling.BOX), np.uint8)


def prepare_mesh(
    mesh: Mesh,
    max_faces: int | None = 4096,
    max_edge_fraction: float | None = None,
    texture_size: int | None = 1024,
) -> Mesh:
    """Prepare a mesh for the JAX rasterizer: decimate, then subdivide long edges.

    Args:
      max_faces: face budget for decimation (None keeps every face).
      max_edge_fraction: after decimation, split edges longer than this fraction of the
        diameter (None skips). Bounds each triangle's size in pixels at a given render scale:
        at ``s`` pixels per diameter no triangle spans more than ``max_edge_fraction * s``
        pixels, so rasterizer windows of that size hold whole triangles.
      texture_size: longest texture side kept (None keeps it); a 4096^2 texture is 200 MB as
        float32 on an accelerator.
    """
    out = mesh
    if max_faces is not None:
        out = decimate(out, max_faces)
    if max_edge_fraction is not None:
        out = subdivide(out, max_edge_fraction * mesh.diameter)
    if texture_size is not None and out.texture is not None:
        out = out.replace(texture=resize_texture(out.texture, texture_size))
    return out


# --------------------------------------------------------------------------------------------
# Padding for the rasterizer


def bucket_size(n: int, minimum: int = 256) -> int:
    """Smallest size >= n in the ladder {2^k, 1.5 * 2^k} (at most 50 % padding), >= minimum."""
    size = minimum
    while size < n:
        size = size * 3 // 2 if (size & (size - 1)) == 0 else size * 4 // 3
    return int(size)


@dataclasses.dataclass(frozen=True)
class RasterMesh:
    """A mesh as per-face device tables for the JAX rasterizer, padded to a size bucket (a pytree).

    Only the face count (bucketed) and the texture shape reach compiled code, so meshes in the
    same face bucket with the same texture shape share one compiled renderer.

    Attributes:
      face_geom: [Fp, 18] per face, object frame, computed in float64: corners v0, v1, v2,
        normal n = e1 x e2 (e_k = v_k - v0), and the dual basis g1 = (e2 x n) / |n|^2,
        g2 = (n x e1) / |n|^2, so that a point X of the plane has barycentrics
        b1 = (X - v0) . g1, b2 = (X - v0) . g2.
      corner_normals: [Fp, 9] unit vertex normals at the three corners.
      corner_colors: [Fp, 9] albedo colours at the corners (the mesh's; grey when it has none,
        white when textured).
      corner_uv: [Fp, 6] texture coordinates at the corners (zeros when untextured).
      face_mask: [Fp] bool, real non-degenerate faces (padding is False).
      texture: [Ht, Wt, 3] uint8 ([1, 1, 3] white when untextured).
      center: [3], radius: [] bounding sphere (mm) for depth ranges; diameter: [] mm.
      cull_backfaces: [] bool, skip faces turned away from the camera (closed meshes).
      has_texture: static flag.
    """

    face_geom: Any
    corner_normals: Any
    corner_colors: Any
    corner_uv: Any
    face_mask: Any
    texture: Any
    center: Any
    radius: Any
    diameter: Any
    cull_backfaces: Any
    has_texture: bool = dataclasses.field(default=False, metadata={"static": True})

    @property
    def num_faces_padded(self) -> int:
        return int(self.face_geom.shape[0])


def _register_raster_mesh():
    import jax

    data = [f.name for f in dataclasses.fields(RasterMesh) if f.name != "has_texture"]
    jax.tree_util.register_dataclass(RasterMesh, data_fields=data, meta_fields=["has_texture"])


_register_raster_mesh()


def to_raster_mesh(
    mesh: Mesh,
    face_bucket: int | None = None,
    cull_backfaces: bool | None = None,
) -> RasterMesh:
    """Per-face tables of a :class:`Mesh` for the JAX rasterizer, padded to a face bucket.

    Args:
      face_bucket: padded face count; None takes :func:`bucket_size` of the face count (at most
        50 % padding). Pass a fixed value to make meshes of different sizes share a compile.
      cull_backfaces: skip triangles facing away from the camera. None decides by
        :func:`is_closed` (culling an open or inconsistently wound mesh would show holes).
    """
    import jax.numpy as jnp

    nf = mesh.num_faces
    nf_p = bucket_size(nf) if face_bucket is None else int(face_bucket)
    if nf_p < nf:
        raise ValueError(f"face_bucket {nf_p} < {nf} faces; decimate the mesh or raise the bucket")

    def pad(a, value=0.0):
        out = np.full((nf_p,) + a.shape[1:], value, a.dtype)
        out[:nf] = a
        return out

    nv = mesh.num_vertices
    if mesh.texture is not None:
        colors, uv, tex = np.ones((nv, 3)), mesh.uv, mesh.texture
    else:
        colors = mesh.colors if mesh.colors is not None else np.full((nv, 3), DEFAULT_GREY)
        uv, tex = np.zeros((nv, 2)), np.full((1, 1, 3), 255, np.uint8)
    if cull_backfaces is None:
        cull_backfaces = is_closed(mesh)
    f = mesh.faces
    tri = mesh.vertices.astype(np.float64)[f]  # [F, 3, 3]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    n = np.cross(e1, e2)
    nn = (n * n).sum(-1)
    ok = nn > 1e-12 * mesh.diameter**4
    inv = np.where(ok, 1.0 / np.where(ok, nn, 1.0), 0.0)[:, None]
    geom = np.concatenate(
        [tri.reshape(-1, 9), n, np.cross(e2, n) * inv, np.cross(n, e1) * inv], -1
    )
    return RasterMesh(
        face_geom=jnp.asarray(pad(geom.astype(np.float32))),
        corner_normals=jnp.asarray(pad(mesh.normals[f].reshape(-1, 9).astype(np.float32))),
        corner_colors=jnp.asarray(pad(np.asarray(colors, np.float32)[f].reshape(-1, 9))),
        corner_uv=jnp.asarray(pad(np.asarray(uv, np.float32)[f].reshape(-1, 6))),
        face_mask=jnp.asarray(pad(ok, False)),
        texture=jnp.asarray(tex),
        center=jnp.asarray(mesh.center, jnp.float32),
        radius=jnp.asarray(mesh.radius, jnp.float32),
        diameter=jnp.asarray(mesh.diameter, jnp.float32),
        cull_backfaces=jnp.asarray(bool(cull_backfaces)),
        has_texture=mesh.texture is not None,
    )
