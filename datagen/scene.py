"""One synthetic scene: compose (meshes, layout, materials, lights, cameras), render, annotate.

The data generator's unit of work (docs/design.md sections 1 and 5; the layouts, meshes and cameras
are in the sibling modules). :func:`generate_scene` builds a scene from a
``np.random.Generator`` and writes it as one BOP scene folder with ``BopSceneWriter``:

1. **Meshes**: ``n`` target instances (``SceneConfig.instances`` on average, uniform in
   (1 +- ``instance_spread``) n) of ``distinct`` (1-20) meshes drawn from the allowed pool
   entries (duplicates of a mesh, as in bin picking; 30 % of the scenes use at most 3), plus
   0-5 procedural distractor primitives. A mesh that cannot be
   used is skipped with a ``MeshSkippedWarning`` and logged; it never aborts the scene.
2. **Layout**: dropped onto a plane or into a bin (MuJoCo), floating, or packed
   (``datagen.layouts``). Distractors take part in the physics.
3. **Appearance** (``datagen.materials``): a random material per instance (or shared by the
   instances of one mesh), a textured ground, textured bin walls, sometimes far backdrop walls,
   a procedural HDR sky and 1-3 point or area lights (re-drawn for every capture; an area
   light that would hide a camera's view is moved away along its ray, :func:`lamp_out_of_view`).
4. **Cameras**: realistic intrinsics (fx != fy); single random views (30 % of them
   close-ups that truncate objects at the image border) or rigs of V calibrated cameras on a
   ring above the scene; ``T_cam_world`` per view.
5. **Rendering** (``MitsubaScene``, path tracing with a fixed seed per image) and, in the same
   call, the instance-id and depth AOVs at exact pixel centres.
6. **Ground truth**: visible masks are the instance-id AOV of the very render (so distractors,
   bin walls and the ground occlude targets but are never annotated); amodal masks are
   ray cast per instance alone (Mitsuba, one kernel per mesh over its instances, in a window
   around each instance's projected hull) on a canvas that extends up to one image size
   beyond every border, as BOP's ``calc_gt_info.py`` does, so truncated objects keep their
   full ``bbox_obj`` and ``px_count_all``. (Mitsuba rather than the JAX rasterizer: window
   sizes vary per instance, which costs Mitsuba a 30 ms kernel build per new bucketed size and
   JAX a multi-second compile per size and mesh bucket.)

Multi-view scenes use BOP's classic scenewise format: every view is its own image id with its
own ``cam_K`` and world extrinsics ``cam_R_w2c``/``cam_t_w2c``; capture ``m`` of a scene holds
image ids ``m * V .. m * V + V - 1`` (all views of a capture share the lighting).

Determinism: everything is drawn from the generator passed in, in a fixed order; Mitsuba renders
with a box reconstruction filter, whose sample accumulation Mitsuba performs as a block
reduction (the Gaussian filter splats with atomic adds, whose float order depends on thread
scheduling: 1e-7 differences that flip uint8 roundings), so a scene is byte-identical run to run
on one machine and software stack.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import pathlib
import shutil
import time
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import trimesh

from datagen import cameras as cams
from datagen import cell as C
from datagen import layouts as L
from datagen import materials as Mt
from datagen.cell import Cell
from datagen.meshes import LoadedMesh, MeshPool, MeshSkippedWarning
from threept_jax.data.bop import BopSceneWriter, Camera, GtInstance
from threept_jax.data.files import atomic_write_bytes
from threept_jax.render.mesh import Mesh, load_mesh
from threept_jax.render.mitsuba_backend import (
    Material,
    MeshRenderError,
    MitsubaRenderer,
    MitsubaScene,
    check_renders,
)

LAYOUTS = ("drop", "float", "pack", "mixed", "cell")
# Mixed layouts: (kind, weight).
_MIXED = (("drop-plane", 0.3), ("drop-bin", 0.3), ("float", 0.15), ("pack-grid", 0.1),
          ("pack-pile", 0.15))
#: Amodal masks are computed on the image grown by this many image sizes on each side (BOP).
CANVAS_MARGIN = 1.0
#: Smallest image side, pixels.
MIN_SIDE = 16
#: Smallest useful path length of Mitsuba's path tracer (-1 is unbounded): 0 renders nothing and
#: 1 only the light sources seen directly (objects black); 2 adds direct illumination.
MIN_MAX_DEPTH = 2


@dataclasses.dataclass(frozen=True)
class SceneConfig:
    """What a scene looks like and how it is rendered.

    Attributes:
      resolution: (W, H) pixels.
      spp: path-tracing samples per pixel.
      views: V cameras per capture (1: independent single views; > 1: a ring rig).
      images_per_scene: M captures per scene (M * V images).
      layout: "drop", "float", "pack", "mixed" (a random one per scene) or "cell" (parts
        dropped into the tray of ``cell`` under its fixed camera, ``datagen/cell.py``).
      instances: mean number of annotated instances per scene.
      instance_spread: the count is uniform in [1 - spread, 1 + spread] x ``instances``.
      distinct: (min, max) number of distinct meshes among them.
      distractors: (min, max) number of unannotated distractor primitives.
      bin_probability: share of drop scenes that use a bin rather than a plane.
      closeup_probability: share of single views aimed at part of the scene (truncation).
      image_format: "jpg" (BOP PBR) or "png" for ``rgb/``.
      depth_scale: mm per unit of the 16-bit depth PNGs (0.1 -> up to 6.5 m, like BOP PBR).
      max_depth: path length of the path tracer: -1 (unbounded) or >= ``MIN_MAX_DEPTH``.
      denoise: clean the path-traced colour with Open Image Denoise fed its albedo and normal
        (``threept_jax/render/denoise.py``); ``bench/datagen_quality.py`` measures the gain.
      texture_size: side of procedural textures, pixels.
      lights: (min, max) number of point / area lights besides the environment.
      cell: the robot cell of the "cell" layout (:func:`datagen.cell.design_cell`), else None.
    """

    resolution: tuple[int, int] = (640, 480)
    spp: int = 4
    views: int = 1
    images_per_scene: int = 1
    layout: str = "mixed"
    instances: int = 30
    instance_spread: float = 0.5
    distinct: tuple[int, int] = (1, 20)
    distractors: tuple[int, int] = (0, 5)
    bin_probability: float = 0.5
    closeup_probability: float = 0.3
    image_format: str = "jpg"
    depth_scale: float = 0.1
    max_depth: int = 6
    denoise: bool = True
    texture_size: int = 256
    lights: tuple[int, int] = (1, 3)
    cell: Cell | None = None

    def __post_init__(self):
        W, H = self.resolution
        if W < MIN_SIDE or H < MIN_SIDE:
            raise ValueError(f"resolution must be at least {MIN_SIDE}x{MIN_SIDE}, got {W}x{H}")
        if self.spp < 1 or self.views < 1 or self.images_per_scene < 1:
            raise ValueError(
                f"spp, views and images per scene must be >= 1, got {self.spp}, {self.views}, "
                f"{self.images_per_scene}"
            )
        if self.layout not in LAYOUTS:
            raise ValueError(f"layout must be one of {LAYOUTS}, got {self.layout!r}")
        if self.instances < 1:
            raise ValueError(f"instances must be >= 1, got {self.instances}")
        for name in ("distinct", "distractors", "lights"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi or (name == "distinct" and lo < 1):
                raise ValueError(f"{name} must be (min, max) with 0 <= min <= max, got {lo, hi}")
        if self.image_format not in ("jpg", "png"):
            raise ValueError(f"image_format must be 'jpg' or 'png', got {self.image_format!r}")
        for name in ("closeup_probability", "bin_probability", "instance_spread"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must lie in [0, 1], got {getattr(self, name)}")
        if self.max_depth != -1 and self.max_depth < MIN_MAX_DEPTH:
            raise ValueError(
                f"max_depth must be -1 (unbounded) or >= {MIN_MAX_DEPTH}, got {self.max_depth}: "
                "Mitsuba's path tracer renders nothing at 0 and only the light sources at 1"
            )
        if not self.depth_scale > 0:
            raise ValueError(f"depth_scale must be > 0 mm per unit, got {self.depth_scale}")
        if (self.layout == "cell") != (self.cell is not None):
            raise ValueError("the cell layout needs its cell (datagen.cell.design_cell), and a "
                             "cell needs layout='cell'")
        if self.cell is not None and (self.views != self.cell.views
                                      or tuple(self.cell.resolution) != tuple(self.resolution)):
            raise ValueError(f"the cell has {self.cell.views} camera(s) of "
                             f"{self.cell.resolution[0]}x{self.cell.resolution[1]}: use "
                             f"views={self.cell.views} and that resolution, got "
                             f"views={self.views}, resolution={self.resolution}")

    @property
    def images(self) -> int:
        """Images per scene (M * V)."""
        return self.images_per_scene * self.views


# --------------------------------------------------------------------------------------------
# Object assets: the dataset model, its render mesh, collision shape and amodal renderer.


def write_ply(
    path: pathlib.Path,
    vertices: np.ndarray,
    faces: np.ndarray,
    colors: np.ndarray | None = None,
    uv: np.ndarray | None = None,
    texture_name: str | None = None,
) -> None:
    """Binary little-endian PLY (float32 xyz, optional uchar rgb and float texture_u/v), atomic.

    The bytes depend only on the arrays, so a model written twice is byte-identical.
    """
    v = np.asarray(vertices, "<f4")
    f = np.asarray(faces, "<i4")
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    header = ["ply", "format binary_little_endian 1.0", "comment threept_jax datagen"]
    if texture_name is not None:
        header.append(f"comment TextureFile {texture_name}")
    header += [f"element vertex {len(v)}", "property float x", "property float y",
               "property float z"]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    if uv is not None:
        fields += [("texture_u", "<f4"), ("texture_v", "<f4")]
        header += ["property float texture_u", "property float texture_v"]
    header += [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    vert = np.zeros(len(v), fields)
    vert["x"], vert["y"], vert["z"] = v[:, 0], v[:, 1], v[:, 2]
    if colors is not None:
        c = np.clip(np.round(np.asarray(colors, np.float64) * 255), 0, 255).astype("u1")
        vert["red"], vert["green"], vert["blue"] = c[:, 0], c[:, 1], c[:, 2]
    if uv is not None:
        vert["texture_u"], vert["texture_v"] = uv[:, 0], uv[:, 1]
    face = np.zeros(len(f), [("n", "u1"), ("i", "<i4", (3,))])
    face["n"] = 3
    face["i"] = f
    data = ("\n".join(header) + "\n").encode() + vert.tobytes() + face.tobytes()
    atomic_write_bytes(path, data)


def _ply_header(path: pathlib.Path) -> tuple[list[str], int]:
    """(header lines, byte length of the header) of a PLY file."""
    with open(path, "rb") as fh:
        head = fh.read(65536)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise ValueError(f"{path} is not a PLY file (no ply magic or end_header)")
    stop = head.index(b"\n", end) + 1
    return head[:stop].decode("ascii", "replace").splitlines(), stop


def copy_bop_model(src: pathlib.Path, dst: pathlib.Path) -> None:
    """Copy a BOP model PLY to ``dst`` with its texture renamed to ``dst``'s stem.

    BOP PLYs name their texture in a ``comment TextureFile`` line; models of different datasets
    share names (obj_000001.png), so the texture is copied as ``<dst stem><ext>`` and the header
    line rewritten (dropped when the texture file is missing, so that the copy can never pick
    up another model's texture). Everything else is copied byte for byte.
    """
    lines, stop = _ply_header(src)
    raw = src.read_bytes()
    if not any(line.split()[:2] == ["comment", "TextureFile"] for line in lines):
        atomic_write_bytes(dst, raw)
        return
    out_lines = []
    for line in lines:
        parts = line.split()
        if len(parts) >= 3 and parts[0] == "comment" and parts[1] == "TextureFile":
            tex = src.parent / parts[2]
            if not tex.is_file():
                continue
            name = dst.stem + tex.suffix.lower()
            atomic_write_bytes(dst.parent / name, tex.read_bytes())
            line = f"comment TextureFile {name}"
        out_lines.append(line)
    atomic_write_bytes(dst, ("\n".join(out_lines) + "\n").encode("ascii") + raw[stop:])


def _has_file_normals(path: pathlib.Path) -> bool:
    try:
        lines, _ = _ply_header(path)
    except (OSError, ValueError):
        return False
    return any(line.split()[:3] == ["property", "float", "nx"] for line in lines)


def export_model(loaded: LoadedMesh, dst: pathlib.Path) -> None:
    """Write the pool mesh ``loaded`` as the dataset model ``dst`` (``models/obj_XXXXXX.ply``).

    BOP models kept in their file frame and units are copied (normals, colours and textures
    preserved); every other mesh (plain files re-centred or scaled to mm, procedural parts) is
    written from the pool's geometry, with vertex colours or a texture when trimesh found them.
    """
    rec = loaded.record
    if (
        rec.path is not None
        and rec.path.suffix.lower() == ".ply"
        and rec.source_obj_id is not None
        and rec.scale == 1.0
        and not rec.recenter
    ):
        copy_bop_model(rec.path, dst)
        return
    m = loaded.mesh
    colors = uv = tex_name = None
    visual = getattr(m, "visual", None)
    if visual is not None and visual.kind == "vertex":
        colors = np.asarray(visual.vertex_colors, np.float64)[:, :3] / 255.0
    elif (visual is not None and visual.kind == "texture"
          and getattr(visual, "uv", None) is not None):
        mat = visual.material
        image = getattr(mat, "image", None) or getattr(mat, "baseColorTexture", None)
        if image is not None and len(visual.uv) == len(m.vertices):
            import io

            buf = io.BytesIO()
            image.convert("RGB").save(buf, format="PNG", optimize=False)
            tex_name = dst.stem + ".png"
            atomic_write_bytes(dst.parent / tex_name, buf.getvalue())
            uv = np.asarray(visual.uv, np.float64)
    write_ply(dst, m.vertices, m.faces, colors, uv, tex_name)


def render_problems(pool: MeshPool, indices: Sequence[int]) -> dict[int, str]:
    """``{index: "file: cause"}`` of the usable pool meshes at ``indices`` that do not path-trace.

    Each mesh takes the route a scene gives it (written as a dataset model, read back) and is
    rendered once in every material kind with its own colours or texture
    (:func:`threept_jax.render.mitsuba_backend.check_renders`), so a mesh Mitsuba refuses is
    named before any data work rather than as a traceback in the middle of it.
    """
    import tempfile

    problems: dict[int, str] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for i in indices:
            loaded = pool.load(i)
            if loaded is None:
                continue
            rec = loaded.record
            dst = pathlib.Path(tmp) / f"obj_{rec.obj_id:06d}.ply"
            try:
                export_model(loaded, dst)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    mesh = load_mesh(dst, models_info=None)
                check_renders(mesh)
            except (MeshRenderError, ValueError, OSError) as e:
                problems[i] = f"{rec.path if rec.path is not None else rec.name}: {e}"
            for f in dst.parent.glob(dst.stem + ".*"):
                f.unlink()
    return problems


@dataclasses.dataclass(frozen=True, eq=False)
class ObjectAsset:
    """A usable pool mesh, ready for a scene.

    Attributes:
      index: position in the pool; obj_id, name: the pool's id and name.
      mesh: the render mesh, loaded from the written dataset model (its frame is the model's).
      shape: collision shape for the layouts.
      hull: [N, 3] convex-hull vertices (object frame, mm), for projected boxes.
      own_appearance: the model has a texture or vertex colours.
      file_normals: the model file stores normals (kept for shading).
    """

    index: int
    obj_id: int
    name: str
    mesh: Mesh
    shape: L.CollisionShape
    hull: np.ndarray
    own_appearance: bool
    file_normals: bool


def _hull_vertices(v: np.ndarray) -> np.ndarray:
    from scipy.spatial import ConvexHull

    try:
        return v[ConvexHull(v).vertices]
    except Exception:  # flat meshes: all vertices bound the projection just as well
        return v


class AssetCache:
    """Loads pool meshes on demand, writes their models, and keeps the prepared assets.

    ``get(index)`` returns an :class:`ObjectAsset`, or None for a mesh that cannot be used (the
    pool rejects it, or exporting, loading or simulating it fails): a ``MeshSkippedWarning`` is
    issued once, and ``bad`` maps its name to the reason. The dataset model of every usable mesh
    is written to ``models_dir/obj_{obj_id:06d}.ply`` (atomically, once).
    """

    def __init__(self, pool: MeshPool, models_dir: pathlib.Path, max_items: int = 256):
        self.pool = pool
        self.models_dir = pathlib.Path(models_dir)
        self.bad: dict[str, str] = {}
        self._bad_index: set[int] = set()
        self._items: collections.OrderedDict[int, ObjectAsset] = collections.OrderedDict()
        self._renderers: collections.OrderedDict[int, MitsubaRenderer] = collections.OrderedDict()
        self._max = max_items

    def model_path(self, obj_id: int) -> pathlib.Path:
        return self.models_dir / f"obj_{obj_id:06d}.ply"

    def get(self, index: int) -> ObjectAsset | None:
        if index in self._bad_index:
            return None
        if index in self._items:
            self._items.move_to_end(index)
            return self._items[index]
        rec = self.pool.records[index]
        loaded = self.pool.load(index)
        if loaded is None:  # the pool warned and counted it
            self._bad_index.add(index)
            self.bad[rec.name] = self.pool.skipped_reasons.get(rec.name, "unusable")
            return None
        try:
            asset = self._prepare(index, loaded)
        except Exception as e:  # a bad mesh is skipped, never fatal
            reason = f"{type(e).__name__}: {e}"
            self._bad_index.add(index)
            self.bad[rec.name] = reason
            warnings.warn(f"skipping mesh {rec.name}: {reason}", MeshSkippedWarning, stacklevel=2)
            return None
        self._items[index] = asset
        if len(self._items) > self._max:
            old, _ = self._items.popitem(last=False)
            self._renderers.pop(old, None)
        return asset

    def _prepare(self, index: int, loaded: LoadedMesh) -> ObjectAsset:
        rec = loaded.record
        dst = self.model_path(rec.obj_id)
        written = not dst.is_file()
        if written:
            dst.parent.mkdir(parents=True, exist_ok=True)
            export_model(loaded, dst)
        try:
            with warnings.catch_warnings():
                # BOP PLYs store every face twice and are rarely watertight; the loader says
                # so for every file, which is noise here.
                warnings.simplefilter("ignore")
                mesh = load_mesh(dst, models_info=None)
            mesh = mesh.replace(name=rec.name)
            tm = trimesh.Trimesh(mesh.vertices.astype(np.float64), mesh.faces, process=False)
            shape = L.collision_shape(tm, name=rec.name)
            check_renders(mesh)  # a mesh Mitsuba refuses is skipped here, not mid-scene
        except Exception:
            if written:  # models/ holds usable meshes only
                for f in dst.parent.glob(dst.stem + ".*"):
                    f.unlink()
            raise
        return ObjectAsset(
            index=index,
            obj_id=rec.obj_id,
            name=rec.name,
            mesh=mesh,
            shape=shape,
            hull=_hull_vertices(np.asarray(mesh.vertices, np.float64)),
            own_appearance=mesh.texture is not None or mesh.colors is not None,
            file_normals=_has_file_normals(dst),
        )

    def renderer(self, asset: ObjectAsset) -> MitsubaRenderer:
        """The ray caster of ``asset`` for amodal masks (one Mitsuba scene per mesh, cached)."""
        r = self._renderers.get(asset.index)
        if r is None:
            r = MitsubaRenderer(asset.mesh)
            self._renderers[asset.index] = r
        return r


# --------------------------------------------------------------------------------------------
# Deterministic path tracing.


# --------------------------------------------------------------------------------------------
# Composition.


@dataclasses.dataclass
class Timings:
    """Wall-clock seconds per stage of a scene (for logs and the benchmark; never written).

    physics: mesh choice and layout (MuJoCo); compose: materials, textures, lights, cameras and
    the Mitsuba scene; render: path tracing plus the instance and depth AOVs; annotate: amodal
    masks; write: BOP files.
    """

    physics: float = 0.0
    compose: float = 0.0
    render: float = 0.0
    annotate: float = 0.0
    write: float = 0.0


def _distractor(rng: np.random.Generator, size: float, index: int) -> tuple[Mesh, trimesh.Trimesh]:
    """A random primitive (box, sphere, cylinder, capsule, cone, torus) about ``size`` mm."""
    kind = ("box", "sphere", "cylinder", "capsule", "cone", "torus")[int(rng.integers(6))]
    s = size * rng.uniform(0.4, 1.0, 3)
    if kind == "box":
        tm = trimesh.creation.box(extents=s)
    elif kind == "sphere":
        tm = trimesh.creation.icosphere(subdivisions=2, radius=s[0] / 2)
    elif kind == "cylinder":
        tm = trimesh.creation.cylinder(radius=s[0] / 2, height=s[1], sections=24)
    elif kind == "capsule":
        tm = trimesh.creation.capsule(height=s[1], radius=s[0] / 3, count=[16, 16])
    elif kind == "cone":
        tm = trimesh.creation.cone(radius=s[0] / 2, height=s[1], sections=24)
    else:
        tm = trimesh.creation.torus(major_radius=s[0] / 2, minor_radius=s[0] / 2 * rng.uniform(
            0.15, 0.4), major_sections=24, minor_sections=12)
    tm.apply_translation(-tm.bounds.mean(0))
    mesh = Mesh(tm.vertices, tm.faces, name=f"distractor_{index}_{kind}")
    return mesh, tm


def _choose_meshes(
    rng: np.random.Generator, assets: AssetCache, candidates: Sequence[int], n: int
) -> tuple[list[ObjectAsset], dict[str, str]]:
    """``n`` distinct usable assets from ``candidates`` in random order, and the meshes skipped."""
    out: list[ObjectAsset] = []
    skipped: dict[str, str] = {}
    for i in rng.permutation(len(candidates)):
        if len(out) == n:
            break
        a = assets.get(int(candidates[int(i)]))
        if a is None:
            name = assets.pool.records[int(candidates[int(i)])].name
            skipped[name] = assets.bad.get(name, "unusable")
            continue
        out.append(a)
    return out, skipped


def _layout(
    rng: np.random.Generator, kind: str, shapes: list[L.CollisionShape], idx: np.ndarray,
    cfg: SceneConfig,
) -> tuple[str, L.Layout]:
    radii = np.array([shapes[i].radius for i in idx])
    footprint = float(((2 * radii) ** 2).sum())
    if kind == "mixed":
        names, w = zip(*_MIXED)
        kind = names[int(rng.choice(len(names), p=np.array(w) / sum(w)))]
    elif kind == "drop":
        kind = "drop-bin" if rng.random() < cfg.bin_probability else "drop-plane"
    elif kind == "pack":
        kind = "pack-grid" if rng.random() < 0.5 else "pack-pile"
    elif kind == "cell":
        return kind, L.drop_layout(rng, shapes, idx, bin=cfg.cell.tray)
    if kind == "drop-plane":
        side = math.sqrt(footprint * rng.uniform(1.0, 3.0))
        a = rng.uniform(1.0, 1.5)
        return kind, L.drop_layout(rng, shapes, idx, area=(side * a, side / a))
    if kind == "drop-bin":
        layers = rng.uniform(0.7, 2.0)
        side = max(math.sqrt(footprint / layers), 2.2 * radii.max())
        a = rng.uniform(1.0, 1.6)
        b = L.Bin((side * a, side / a), height=max(40.0, 2 * radii.max() * rng.uniform(0.6, 1.5)),
                  wall=float(rng.uniform(5.0, 15.0)))
        return kind, L.drop_layout(rng, shapes, idx, bin=b)
    if kind == "float":
        side = (float(((2 * radii) ** 3).sum()) * rng.uniform(3.0, 8.0)) ** (1 / 3)
        half = (side / 2, side / 2, side / 2)
        return kind, L.float_layout(rng, shapes, idx, center=(0.0, 0.0, side / 2 + 50.0),
                                    half_extents=half)
    return kind, L.pack_layout(rng, shapes, idx, mode=kind.split("-")[1])


def _light_color(rng: np.random.Generator) -> np.ndarray:
    """A near-white light colour (warm to cool), linear RGB with unit mean."""
    warm = rng.uniform(-1, 1)
    c = np.array([1.0 + 0.15 * warm, 1.0, 1.0 - 0.2 * warm])
    return c / c.mean()


def lamp_corners(pos: np.ndarray, centre: np.ndarray, size: Sequence[float]) -> np.ndarray:
    """World corners [4, 3] (mm) of a rectangular lamp of ``size`` (w, h) mm at ``pos`` facing
    ``centre`` (the rectangle :meth:`MitsubaScene.add_area_light` draws there)."""
    T = np.linalg.inv(cams.look_at_camera(pos, centre))
    xy = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * np.asarray(size, np.float64) / 2
    return xy @ T[:3, :2].T + T[:3, 3]


def _clip_depth(poly: np.ndarray, z: float, keep_nearer: bool) -> np.ndarray:
    """The convex polygon ``poly`` [n, 3] (camera frame) clipped to depth >= ``z`` (or <= ``z``
    with ``keep_nearer``): Sutherland-Hodgman against one plane."""
    out = []
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        a_in, b_in = (a[2] <= z, b[2] <= z) if keep_nearer else (a[2] >= z, b[2] >= z)
        if a_in:
            out.append(a)
        if a_in != b_in:
            out.append(a + (z - a[2]) / (b[2] - a[2]) * (b - a))
    return np.array(out).reshape(-1, 3)


def hides_view(corners: np.ndarray, K: np.ndarray, T_cam_world: np.ndarray,
               hw: tuple[int, int], depth: float, near: float = 1.0) -> bool:
    """Whether the planar convex polygon ``corners`` [n, 3] (world, mm) covers any of the image
    of the camera (K, T_cam_world, ``hw``) between ``near`` and ``depth`` mm in front of it
    (what it would hide there): the polygon clipped to that slab, projected, tested against the
    image rectangle for a separating axis."""
    c = corners @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    c = _clip_depth(_clip_depth(c, near, keep_nearer=False), depth, keep_nearer=True)
    if len(c) < 3:
        return False
    uv = (c @ K.T)[:, :2] / c[:, 2:]
    h, w = hw
    image = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
    for shape in (uv, image):
        edges = np.roll(shape, -1, axis=0) - shape
        for axis in np.stack([-edges[:, 1], edges[:, 0]], -1):
            p, q = uv @ axis, image @ axis
            if p.max() < q.min() or q.max() < p.min():
                return False
    return True


def lamp_out_of_view(pos: np.ndarray, centre: np.ndarray, size: Sequence[float],
                     Ks: Sequence[np.ndarray], T_cam_worlds: Sequence[np.ndarray],
                     hw: tuple[int, int], step: float = 1.25, tries: int = 12) -> float | None:
    """How far (a factor of its distance from ``centre``, 1 where it stays) a rectangular lamp
    of ``size`` mm drawn at ``pos`` (facing ``centre``) must move away along its ray so that it
    hides no camera's view of the scene (:func:`hides_view` up to the centre's depth):
    factors of ``step``, None if it never clears. A lamp drawn between a cell's camera and the
    tray hid the whole view behind its unlit back (3 of 48 held-out cell images were black).
    No random draw: the scenes whose lamps hide nothing stay byte-identical."""
    pos = np.asarray(pos, np.float64)
    cameras = [(np.asarray(K, np.float64), np.asarray(T, np.float64),
                float((T[:3, :3] @ centre + T[:3, 3])[2])) for K, T in zip(Ks, T_cam_worlds)]
    for i in range(tries):
        corners = lamp_corners(centre + step**i * (pos - centre), centre, size)
        if not any(hides_view(corners, K, T, hw, depth) for K, T, depth in cameras):
            return step**i
    return None


def _bucket(n: int) -> int:
    """Smallest size >= n in {8, 12, 16, 24, 32, 48, ...} (few distinct kernel sizes)."""
    s = 8
    while s < n:
        s = s * 3 // 2 if s & (s - 1) == 0 else s * 4 // 3
    return s


def amodal_masks(
    assets: AssetCache,
    objs: Sequence[ObjectAsset],
    T_cam_obj: np.ndarray,
    K: np.ndarray,
    hw: tuple[int, int],
    margin: float = CANVAS_MARGIN,
    near: float = 1.0,
) -> tuple[np.ndarray, tuple[int, int]]:
    """Full silhouettes of instances rendered alone: (masks [O, Hc, Wc] bool, offset (x, y)).

    The canvas covers the image and every instance's projected box, clipped to the image grown
    by ``margin`` image sizes on each side; image pixel (0, 0) is canvas pixel ``offset``.
    Each instance is ray cast (pixel centres, exact K) only in a window around the projection of
    its convex hull; instances of one mesh share one kernel (windows padded to a common bucketed
    size so that few kernel sizes are ever compiled).
    """
    H, W = hw
    lo_x, lo_y = -int(round(margin * W)), -int(round(margin * H))
    hi_x, hi_y = W + int(round(margin * W)), H + int(round(margin * H))
    boxes: list[tuple[int, int, int, int] | None] = []
    for obj, T in zip(objs, T_cam_obj):
        X = obj.hull @ T[:3, :3].T + T[:3, 3]
        if (X[:, 2] <= near).all():
            boxes.append(None)  # entirely behind the camera
            continue
        if (X[:, 2] <= near).any():
            x0, y0, x1, y1 = lo_x, lo_y, hi_x - 1, hi_y - 1  # crosses the camera plane
        else:
            uv = (X @ K.T)[:, :2] / X[:, 2:3]
            x0, y0 = (int(math.floor(c)) - 1 for c in uv.min(0))
            x1, y1 = (int(math.ceil(c)) + 1 for c in uv.max(0))
        x0, y0, x1, y1 = max(x0, lo_x), max(y0, lo_y), min(x1, hi_x - 1), min(y1, hi_y - 1)
        boxes.append((x0, y0, x1, y1) if x0 <= x1 and y0 <= y1 else None)
    cx0 = min([0] + [b[0] for b in boxes if b])
    cy0 = min([0] + [b[1] for b in boxes if b])
    cx1 = max([W - 1] + [b[2] for b in boxes if b])
    cy1 = max([H - 1] + [b[3] for b in boxes if b])
    out = np.zeros((len(objs), cy1 - cy0 + 1, cx1 - cx0 + 1), bool)
    groups: dict[int, list[int]] = collections.defaultdict(list)
    for k, (obj, b) in enumerate(zip(objs, boxes)):
        if b is not None:
            groups[obj.index].append(k)
    for ks in groups.values():
        wb = _bucket(max(boxes[k][2] - boxes[k][0] + 1 for k in ks))
        hb = _bucket(max(boxes[k][3] - boxes[k][1] + 1 for k in ks))
        Ks = np.repeat(np.asarray(K, np.float64)[None], len(ks), 0)
        Ks[:, 0, 2] -= [boxes[k][0] for k in ks]
        Ks[:, 1, 2] -= [boxes[k][1] for k in ks]
        res = assets.renderer(objs[ks[0]]).render(
            np.asarray(T_cam_obj[ks], np.float64), Ks, (hb, wb), ("mask",), near=near
        )["mask"]
        for j, k in enumerate(ks):
            x0, y0, x1, y1 = boxes[k]
            out[k, y0 - cy0 : y1 - cy0 + 1, x0 - cx0 : x1 - cx0 + 1] = res[
                j, : y1 - y0 + 1, : x1 - x0 + 1
            ]
    return out, (-cx0, -cy0)


@dataclasses.dataclass(frozen=True)
class SceneResult:
    """What :func:`generate_scene` did: a JSON-able ``info`` (written beside the scene as
    ``datagen_info.json``), the assets used, per-stage timings, and the Mitsuba scene and
    camera (K, T_cam_world, hw) of the last view (benchmarks and debugging)."""

    info: dict[str, Any]
    objects: tuple[ObjectAsset, ...]
    timings: Timings
    last_view: tuple[MitsubaScene, np.ndarray, np.ndarray, tuple[int, int]] | None = None


def generate_scene(
    scene_dir: pathlib.Path,
    scene_id: int,
    rng: np.random.Generator,
    assets: AssetCache,
    candidates: Sequence[int],
    cfg: SceneConfig,
    on_image: Callable[[], None] | None = None,
) -> SceneResult:
    """Compose, render, annotate and write one BOP scene into ``scene_dir``.

    ``candidates`` are the pool indices this scene may use (the split's meshes). ``on_image`` is
    called after every image is written (progress bars). Raises RuntimeError when no candidate
    mesh is usable.
    """
    timings = Timings()
    W, H = cfg.resolution
    t0 = time.perf_counter()
    # -- meshes -------------------------------------------------------------------------------
    mean = cfg.instances
    spread = cfg.instance_spread
    n_inst = int(rng.integers(max(1, math.ceil((1 - spread) * mean)),
                              max(1, math.floor((1 + spread) * mean)) + 1))
    lo, hi = cfg.distinct
    n_inst = max(n_inst, lo)
    if rng.random() < 0.3:  # bin picking: few distinct meshes, many duplicates
        hi = min(hi, max(lo, 3))
    n_distinct = int(rng.integers(lo, max(lo, min(hi, n_inst)) + 1))
    chosen, skipped = _choose_meshes(rng, assets, candidates, n_distinct)
    if not chosen:
        raise RuntimeError(
            f"scene {scene_id}: none of the {len(candidates)} candidate meshes is usable "
            f"(skipped: {skipped}); check the --meshes folders and the split"
        )
    n_distinct = len(chosen)
    median_d = float(np.median([a.mesh.diameter for a in chosen]))
    n_dis = int(rng.integers(cfg.distractors[0], cfg.distractors[1] + 1))
    distractors = [_distractor(rng, median_d * rng.uniform(0.4, 1.2), k) for k in range(n_dis)]
    dis_shapes = [L.collision_shape(tm, name=m.name) for m, tm in distractors]
    shapes = [a.shape for a in chosen] + dis_shapes
    idx = L.choose_instances(rng, n_distinct, n_inst, num_distinct=n_distinct)
    idx = np.concatenate([idx, n_distinct + np.arange(n_dis)])
    idx = idx[rng.permutation(len(idx))]
    # -- layout -------------------------------------------------------------------------------
    kind, lay = _layout(rng, cfg.layout, shapes, idx, cfg)
    is_target = lay.mesh_index < n_distinct
    t_idx = lay.mesh_index[is_target]
    d_idx = lay.mesh_index[~is_target] - n_distinct
    T_wo_t = lay.T_world_obj[is_target]
    T_wo_d = lay.T_world_obj[~is_target]
    targets = [chosen[i] for i in t_idx]
    t_compose = time.perf_counter()
    timings.physics += t_compose - t0

    # -- appearance ---------------------------------------------------------------------------
    shared = {a.index: rng.random() < 0.5 for a in chosen}
    mesh_look = {
        a.index: Mt.random_appearance(rng, a.mesh.diameter, has_own_appearance=a.own_appearance,
                                      texture_size=cfg.texture_size)
        for a in chosen
    }
    looks = [
        mesh_look[a.index] if shared[a.index] else Mt.random_appearance(
            rng, a.mesh.diameter, has_own_appearance=a.own_appearance,
            texture_size=cfg.texture_size)
        for a in targets
    ]
    pts = [a.hull @ T[:3, :3].T + T[:3, 3] for a, T in zip(targets, T_wo_t)]
    pts += [distractors[i][0].vertices @ T[:3, :3].T + T[:3, 3] for i, T in zip(d_idx, T_wo_d)]
    all_pts = np.concatenate(pts) if pts else np.zeros((1, 3))
    centre, radius = cams.bounding_sphere(all_pts)
    radius = max(radius, median_d / 2)
    support = lay.support
    ground_z = support.plane_z
    if ground_z is None and rng.random() < 0.7:
        ground_z = float(all_pts[:, 2].min() - rng.uniform(20.0, 300.0))
    background: list[tuple[Mesh, Material]] = []
    if ground_z is not None:
        _, tex = Mt.random_texture(rng, 2 * cfg.texture_size)
        # At most 7 m across (2 x 2 pieces): beyond it the sky takes over.
        tiles = Mt.ground_plane(ground_z, float(np.clip(8 * radius, 1750.0, 3500.0)), tex,
                                float(rng.uniform(1.0, 4.0) * radius))
        gl = Mt.random_appearance(rng, radius)
        background += [(t, dataclasses.replace(gl.material, color=None)) for t in tiles]
    if support.bin is not None:
        bl = Mt.random_appearance(rng, radius)
        walls = L.Support(plane_z=support.plane_z, bin=support.bin).meshes()[1:]
        for w in walls:
            m = Mesh(w.vertices, w.faces, name="bin_wall")
            background.append((Mt.box_uv_mesh(m, bl.texture, bl.texture_mm, rng), bl.material))
    if cfg.cell is None and rng.random() < 0.4:  # a cell camera looks down: no backdrop
        _, tex = Mt.random_texture(rng, cfg.texture_size)
        z0 = ground_z if ground_z is not None else float(all_pts[:, 2].min() - 500.0)
        dist = float(min(radius * rng.uniform(3.0, 6.0), 3400.0))
        for w in Mt.backdrop_walls(centre, dist, dist * rng.uniform(0.7, 2.0), z0, tex,
                                   float(rng.uniform(1.0, 4.0) * radius)):
            background.append((w, Material("diffuse")))
    target_meshes = [
        Mt.box_uv_mesh(a.mesh, look.texture, look.texture_mm, rng, keep_normals=a.file_normals)
        for a, look in zip(targets, looks)
    ]
    dis_looks = [Mt.random_appearance(rng, median_d, texture_size=cfg.texture_size)
                 for _ in d_idx]
    dis_meshes = [
        Mt.box_uv_mesh(distractors[i][0], look.texture, look.texture_mm, rng)
        for i, look in zip(d_idx, dis_looks)
    ]

    timings.compose += time.perf_counter() - t_compose

    # -- captures -----------------------------------------------------------------------------
    writer = BopSceneWriter(scene_dir, image_ext=cfg.image_format)
    has_floor = ground_z is not None
    for m in range(cfg.images_per_scene):
        t1 = time.perf_counter()
        scene = MitsubaScene(max_depth=cfg.max_depth)
        for mesh, look, T in zip(target_meshes, looks, T_wo_t):
            scene.add_object(mesh, T, look.material)
        for mesh, look, T in zip(dis_meshes, dis_looks, T_wo_d):
            scene.add_object(mesh, T, look.material)
        for mesh, mat in background:
            scene.add_object(mesh, np.eye(4), mat)
        sky, T_env = Mt.sky_environment(rng)
        # A cell is lit mostly by its own lamps above the tray; the room adds a little.
        scene.set_environment(sky, float(rng.uniform(*((0.1, 0.5) if cfg.cell else (0.3, 1.5)))),
                              T_env)
        lamps = []  # (position, distance, irradiance, colour, area size or None for a point)
        for _ in range(int(rng.integers(cfg.lights[0], cfg.lights[1] + 1))):
            if cfg.cell is None:
                el = math.radians(rng.uniform(20.0, 85.0))
                dist = max(300.0, radius * rng.uniform(2.0, 6.0))
            else:  # lamps above the tray, around the camera
                el = math.radians(rng.uniform(55.0, 90.0))
                dist = cfg.cell.working_distance * rng.uniform(0.8, 2.0)
            az = rng.uniform(0, 2 * math.pi)
            pos = centre + dist * np.array(
                [math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]
            )
            irradiance = rng.uniform(0.3, 3.0)
            color = _light_color(rng)
            size = None if rng.random() < 0.5 else radius * rng.uniform(0.3, 1.5, 2)
            lamps.append((pos, dist, irradiance, color, size))
        if cfg.cell is not None:
            Ks, Ts = C.capture(rng, cfg.cell)
        elif cfg.views == 1:
            K = cams.sample_intrinsics(rng, W, H)
            aim, r = centre, radius
            closeup = bool(targets) and rng.random() < cfg.closeup_probability
            if closeup:
                k = int(rng.integers(len(targets)))
                aim = T_wo_t[k][:3, :3] @ targets[k].mesh.center + T_wo_t[k][:3, 3]
                r = max(targets[k].mesh.radius, radius * rng.uniform(0.15, 0.5))
            # Views into a bin from low down would see its walls only (close-ups even more so).
            if support.bin is not None:
                elev = (55.0, 90.0) if closeup else (35.0, 90.0)
            else:
                elev = (20.0, 90.0) if has_floor else (-40.0, 90.0)
            Ks = K[None]
            Ts = cams.sample_view(rng, K, W, H, aim, r, elevation_deg=elev,
                                  distance_scale=(1.0, 1.25), target_jitter=0.15)[None]
        else:
            Ks, Ts = cams.ring_rig(rng, cfg.views, W, H, centre, radius)
        for pos, dist, irradiance, color, size in lamps:
            if size is None:  # a point: nothing a camera could see
                scene.add_point_light(pos, irradiance * dist**2 * color)
                continue
            away = lamp_out_of_view(pos, centre, size, Ks, Ts, (H, W))
            if away is None:
                continue
            if away != 1.0:
                pos, dist = centre + away * (pos - centre), away * dist
            # A camera at the lamp looking at the centre: its +z is the emission axis.
            T_light = np.linalg.inv(cams.look_at_camera(pos, centre))
            scene.add_area_light(T_light, (float(size[0]), float(size[1])),
                                 irradiance * dist**2 / (size[0] * size[1]) * color)
        seeds = rng.integers(0, 2**31 - 1, len(Ks))
        keys = rng.uniform(0.12, 0.3, len(Ks))
        timings.compose += time.perf_counter() - t1
        for v, (K, T_cw) in enumerate(zip(Ks, Ts)):
            im_id = m * cfg.views + v
            t2 = time.perf_counter()
            out = scene.render(K, T_cw, (H, W), spp=cfg.spp, seed=int(seeds[v]),
                               outputs=("rgb", "depth", "instance"), linear=True,
                               denoise=cfg.denoise)
            rgb = Mt.to_uint8_srgb(Mt.auto_exposure(out["rgb"], float(keys[v])))
            t3 = time.perf_counter()
            timings.render += t3 - t2
            T_co = np.einsum("ij,ojk->oik", T_cw, T_wo_t) if targets else np.zeros((0, 4, 4))
            visib = out["instance"][None] == np.arange(1, len(targets) + 1)[:, None, None]
            full, off = amodal_masks(assets, targets, T_co, K, (H, W))
            ox, oy = off
            # The scene and the per-mesh ray casts intersect the same triangles in different
            # frames; a silhouette pixel may differ by float rounding. Visible pixels are part
            # of the object, so they belong to its amodal mask.
            full[:, oy : oy + H, ox : ox + W] |= visib
            masks = full[:, oy : oy + H, ox : ox + W]
            depth = out["depth"].astype(np.float64)
            depth[depth / cfg.depth_scale > 65535] = 0.0  # beyond the PNG range: no depth
            t4 = time.perf_counter()
            timings.annotate += t4 - t3
            gts = [GtInstance(a.obj_id, T) for a, T in zip(targets, T_co)]
            writer.add_image(im_id, Camera(K, cfg.depth_scale, T_cw), rgb, gts, masks, visib,
                             depth, masks_full=full, full_offset=off)
            timings.write += time.perf_counter() - t4
            if on_image is not None:
                on_image()
    t5 = time.perf_counter()
    writer.close()
    timings.write += time.perf_counter() - t5
    used = sorted({a.obj_id: a for a in targets}.values(), key=lambda a: a.obj_id)
    info = {
        "scene_id": int(scene_id),
        "layout": kind,
        "settled": bool(lay.settled),
        "removed_instances": int(lay.removed),
        "num_targets": len(targets),
        "num_distractors": len(d_idx),
        "views": cfg.views,
        "captures": cfg.images_per_scene,
        "objects": {str(a.obj_id): a.name for a in used},
        "materials": [look.label for look in looks],
        "skipped_meshes": dict(sorted(skipped.items())),
    }
    return SceneResult(info, tuple(used), timings, (scene, Ks[-1], Ts[-1], (H, W)))


def remove_tree(path: pathlib.Path) -> None:
    """Delete a partial scene folder (resume)."""
    shutil.rmtree(path, ignore_errors=False)
