"""The refiner's training input: a grain pipeline of 3PT-R examples, one instance with J poses.

Built like :mod:`threept_jax.data.detector_input` (whose record decoding, object table and crop
helpers it reuses) from picklable grain transforms and :func:`refiner_dataset`, over the
ArrayRecord shards of a records folder (``<records_dir>/<split>/*.array_record`` and
``objects.json``, whose rows need the ``mesh`` path ``datagen.pack`` writes):

1. :class:`~threept_jax.data.detector_input.DecodeExample` - record bytes -> annotated image.
2. :class:`SampleInstance` - picks an instance with ``visib_fract >= min_visib`` (uniformly
   among those), draws J hypotheses around its ground truth (below), crops the image around
   the *first* hypothesis and resamples the instance's visible mask to the map size.

**Views.** Every example is a single view (V = 1): ``T_cam_world`` is the identity and poses are
given as ``T_world_obj = T_cam_obj``. Rigs (V > 1) would group the records of one capture
(same ``scene_id`` and ``im_id``, each with its own ``K`` and ``T_cam_world``) in a transform
before step 2 and stack the per-view fields on V; the fields already carry the V axis so the
trainer and :func:`threept_jax.pipeline.refinement.refine_step` need no change for them.

**Hypotheses** (J = ``num_hypotheses``, all perturbed, none exactly the ground truth), in the
camera frame, about the bounding-sphere centre c (object frame) so that the rotation does not
move the object in the image: ``R = R_delta R_gt`` and the centre moves from
``c_gt = R_gt c + t_gt`` to ``c_gt + d``, i.e. ``t = c_gt + d - R c``, with

* ``R_delta`` a rotation about an axis uniform on the sphere by an angle
  ``min(|N(0, rotation_sigma_deg)|, rotation_max_deg)`` (half-normal, sigma 15 degrees, clipped
  at 45: mean 12.0 degrees, 95 % under 29.4; MegaPose's coarse-to-refiner noise is of this
  order);
* ``d = (dx, dy, dz)`` with ``dx, dy ~ N(0, xy_sigma * diameter)`` (0.02 of the diameter) and
  ``dz ~ N(0, z_sigma * z)`` (0.05 of the ground-truth centre depth z).

Draws come from grain's per-element generator (seed, element index): deterministic.

**Crop.** The square box :func:`~threept_jax.geometry.framing.crop_boxes` (margin
``crop_margin``) of the first hypothesis, which all J share, as inference crops around its
current best hypothesis. The image is resampled to ``crop_size`` by
:func:`~threept_jax.data.detector_input.warp_crop` (bilinear, antialiased, zeros outside the
image), ``crop_K`` is :func:`~threept_jax.geometry.camera.crop_intrinsics` of the box. The
visible mask (``instances == index + 1``) is resampled to the h x w map by nearest neighbour
with pixel-centre alignment: map pixel (i, j) is crop point ((j + 0.5) W / w - 0.5,
(i + 0.5) H / h - 0.5), i.e. source pixel ``x0 + (j + 0.5) side / w - 0.5`` (column), rounded;
outside the image it is False.

**Images without an instance at ``min_visib``** (or without any instance) give an example with
``valid = False``: zero crops and mask, a placeholder pose (identity rotation, 5 diameters in
front of the camera) for the ground truth and every hypothesis. The trainer leaves such
examples out of every loss (the losses' ``valid``); an instance under ``min_visib`` is never
the example.

Example fields (V = 1, J = ``num_hypotheses``, H = W = ``crop_size``, h = w = ``output_size``,
Ns = ``max_symmetries``): ``crops`` uint8 [V, H, W, 3], ``crop_K`` float32 [V, 3, 3],
``T_cam_world`` float32 [V, 4, 4], ``T_world_obj_gt`` float32 [4, 4], ``hypotheses`` float32
[J, 4, 4], ``visible_mask`` bool [V, h, w], ``obj_id`` int32, ``mesh_index`` int32 (row of the
object in :class:`RefinerMeshes`), ``diameter`` float32 (mm), ``symmetries`` float32
[Ns, 4, 4] and ``symmetry_mask`` bool [Ns] (padded as the detector pipeline pads them),
``visib`` float32, ``valid`` bool, ``scene_id`` and ``im_id`` int32.

**Meshes for the jitted step.** :class:`RefinerMeshes` loads every object's mesh, prepares it
(``render.mesh.prepare_mesh``: decimation to ``max_faces``) and pads all of them to ONE face
budget, ``bucket_size`` of the largest prepared face count, so a single compiled renderer
serves every object; the RasterMesh fields are stacked on a leading object axis. Inside a
jitted step, ``meshes.take(batch["mesh_index"][b])`` (``jax.tree.map(lambda x: x[i], stacked)``,
``i`` may be traced) is one object's RasterMesh, and ``jax.vmap`` over the indices gives a
batch of them. Textures share one shape: when any object is textured, every texture is resized
to ``texture_size`` squared and untextured objects get a white one (the renderer multiplies the
vertex colour by the texture, so they render as before).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import pathlib
from collections.abc import Mapping
from typing import Any, NamedTuple

import cv2
import grain
import jax
import jax.numpy as jnp
import numpy as np

from threept_jax.data.banks import ObjectEntry, bank_symmetries, load_object_table
from threept_jax.data.detector_input import (
    BankCache,
    decoded_records,
    pad_symmetries,
    warp_crop,
)
from threept_jax.data.ply import load_ply_vertices
from threept_jax.geometry.camera import crop_intrinsics
from threept_jax.geometry.framing import crop_boxes
from threept_jax.render.mesh import RasterMesh, bucket_size, load_mesh, prepare_mesh, to_raster_mesh

__all__ = [
    "RefinerExampleConfig", "RefinerMeshes", "SampleInstance", "Sphere", "load_mesh_paths",
    "object_spheres", "perturb_poses", "refiner_dataset", "resample_mask",
]


@dataclasses.dataclass(frozen=True)
class RefinerExampleConfig:
    """How a 3PT-R example is cut from an annotated image (module docstring).

    Attributes:
      crop_size: H = W of the real crop (``RefinerConfig.crop_size``).
      output_size: h = w of the visible mask (``RefinerConfig.output_size``).
      num_hypotheses: J poses per instance.
      min_visib: an instance can be an example when its visib_fract is at least this.
      max_symmetries: Ns; objects with more symmetry transforms keep Ns evenly spaced ones.
      crop_margin: ``crop_boxes``' half-side over the projected bounding-sphere radius.
      rotation_sigma_deg, rotation_max_deg: the rotation noise's half-normal sigma and clip.
      xy_sigma: sigma of the x and y translation noise, in diameters.
      z_sigma: sigma of the z translation noise, as a share of the centre's depth.
    """

    crop_size: int = 224
    output_size: int = 56
    num_hypotheses: int = 5
    min_visib: float = 0.3
    max_symmetries: int = 64
    crop_margin: float = 1.2
    rotation_sigma_deg: float = 15.0
    rotation_max_deg: float = 45.0
    xy_sigma: float = 0.02
    z_sigma: float = 0.05

    def __post_init__(self):
        for name in ("crop_size", "output_size", "num_hypotheses", "max_symmetries"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0.0 <= self.min_visib <= 1.0:
            raise ValueError(f"min_visib must be in [0, 1], got {self.min_visib}")
        if not self.crop_margin > 0:
            raise ValueError(f"crop_margin must be > 0, got {self.crop_margin}")
        for name in ("rotation_sigma_deg", "rotation_max_deg", "xy_sigma", "z_sigma"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")


class Sphere(NamedTuple):
    """Bounding sphere (object frame, mm): what ``crop_boxes`` reads of a mesh."""

    center: np.ndarray
    radius: float


@functools.partial(jax.jit, static_argnames=("margin", "size"))
def crop_frame(sphere: Sphere, T_cam_obj, K, margin: float, size: int):
    """The crop of one example: :func:`~threept_jax.geometry.framing.crop_boxes`' box [4]
    (pixel-edge xyxy) around ``sphere`` projected at ``T_cam_obj`` [4, 4] by the image's ``K``
    [3, 3], and :func:`~threept_jax.geometry.camera.crop_intrinsics` of it resized to ``size``
    (float32 [3, 3]). One compiled call: run op by op, their few dozen small operations took
    most of an example's sampling (``bench/refiner_step.py --records``)."""
    box = crop_boxes(sphere, T_cam_obj, jnp.eye(4)[None], K[None], margin=margin)[0]
    return box, crop_intrinsics(K, box, (size, size))


# --------------------------------------------------------------------------- meshes


def load_mesh_paths(records_dir) -> dict[int, pathlib.Path]:
    """{obj_id: absolute mesh path} from the ``mesh`` field of ``<records_dir>/objects.json``."""
    path = pathlib.Path(records_dir) / "objects.json"
    load_object_table(records_dir)  # the table's own checks and errors first
    raw = json.loads(path.read_text())
    out = {}
    for key, row in raw.items():
        mesh = row.get("mesh") if isinstance(row, dict) else None
        if not isinstance(mesh, str) or not mesh:
            raise ValueError(
                f"{path} object {key}: no 'mesh' path; the refiner renders the object's CAD "
                "model, so its row needs \"mesh\": \"models/obj_<id>.ply\" (re-pack the records "
                "with `python -m datagen.pack`, which copies the models and writes the field)")
        out[int(key)] = (path.parent / mesh).resolve()
    return out


def object_spheres(records_dir) -> dict[int, Sphere]:
    """{obj_id: bounding sphere} of the table's meshes (``Mesh.center`` / ``Mesh.radius`` rule:
    centre of the axis-aligned box, radius to the farthest vertex)."""
    out = {}
    for obj_id, path in load_mesh_paths(records_dir).items():
        if not path.is_file():
            raise FileNotFoundError(f"mesh {path} of object {obj_id} (objects.json of "
                                    f"{records_dir}) not found")
        v = (load_ply_vertices(path) if path.suffix.lower() == ".ply"
             else load_mesh(path, models_info=None).vertices).astype(np.float64)
        c = (v.min(0) + v.max(0)) / 2
        out[obj_id] = Sphere(c.astype(np.float32), float(np.linalg.norm(v - c, axis=1).max()))
    return out


@dataclasses.dataclass(frozen=True)
class RefinerMeshes:
    """Every object's RasterMesh padded to one face budget and stacked (module docstring).

    Attributes:
      obj_ids: int [O], sorted; row i of ``stacked`` is object ``obj_ids[i]``.
      stacked: a :class:`RasterMesh` whose array fields have a leading [O] axis.
    """

    obj_ids: np.ndarray
    stacked: RasterMesh

    @classmethod
    def from_records(cls, records_dir, *, max_faces: int | None = 4096,
                     texture_size: int = 256) -> RefinerMeshes:
        """Load, prepare (decimate to ``max_faces``) and pad the meshes of ``objects.json``."""
        paths = load_mesh_paths(records_dir)
        meshes = {k: prepare_mesh(load_mesh(p, models_info=None), max_faces=max_faces,
                                  texture_size=None) for k, p in sorted(paths.items())}
        return cls.from_meshes(meshes, texture_size=texture_size)

    @classmethod
    def from_meshes(cls, meshes: Mapping[int, Any], *, texture_size: int = 256
                    ) -> RefinerMeshes:
        """Stack prepared :class:`~threept_jax.render.mesh.Mesh` objects {obj_id: mesh}."""
        if not meshes:
            raise ValueError("no meshes to stack")
        ids = sorted(int(k) for k in meshes)
        budget = bucket_size(max(meshes[k].num_faces for k in ids))
        rasters = [to_raster_mesh(meshes[k], face_bucket=budget) for k in ids]
        if any(r.has_texture for r in rasters):
            s = int(texture_size)
            rasters = [dataclasses.replace(
                r, has_texture=True,
                texture=jnp.asarray(cv2.resize(np.asarray(r.texture), (s, s),
                                               interpolation=cv2.INTER_AREA))
                if r.has_texture else jnp.full((s, s, 3), 255, jnp.uint8))
                for r in rasters]
        stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *rasters)
        return cls(obj_ids=np.asarray(ids, np.int64), stacked=stacked)

    @property
    def face_budget(self) -> int:
        return int(self.stacked.face_geom.shape[1])

    def index(self, obj_id: int) -> int:
        """Row of ``obj_id`` (what the examples' ``mesh_index`` holds)."""
        i = int(np.searchsorted(self.obj_ids, obj_id))
        if i >= len(self.obj_ids) or self.obj_ids[i] != obj_id:
            raise KeyError(f"object {obj_id} has no mesh (objects: {self.obj_ids.tolist()})")
        return i

    def take(self, i) -> RasterMesh:
        """Row i's RasterMesh; ``i`` may be a traced integer inside ``jit``/``vmap``."""
        return jax.tree.map(lambda x: x[i], self.stacked)


# --------------------------------------------------------------------------- pieces


def perturb_poses(T_cam_obj: np.ndarray, center: np.ndarray, diameter: float, num: int,
                  config: RefinerExampleConfig, rng: np.random.Generator) -> np.ndarray:
    """float64 [num, 4, 4] noisy copies of T_cam_obj [4, 4] (module docstring, Hypotheses)."""
    cfg = config
    T = np.asarray(T_cam_obj, np.float64)
    c = np.asarray(center, np.float64)
    axis = rng.standard_normal((num, 3))
    axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12)
    angle = np.minimum(np.abs(rng.normal(0.0, cfg.rotation_sigma_deg, num)),
                       cfg.rotation_max_deg)
    # Rodrigues: R = I + sin(a) [n]x + (1 - cos(a)) [n]x^2.
    a = np.radians(angle)[:, None, None]
    nx = np.zeros((num, 3, 3))
    nx[:, 0, 1], nx[:, 0, 2], nx[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    nx -= nx.transpose(0, 2, 1)
    R_delta = np.eye(3) + np.sin(a) * nx + (1 - np.cos(a)) * (nx @ nx)
    c_gt = T[:3, :3] @ c + T[:3, 3]
    d = np.stack([rng.normal(0.0, cfg.xy_sigma * diameter, num),
                  rng.normal(0.0, cfg.xy_sigma * diameter, num),
                  rng.normal(0.0, cfg.z_sigma * abs(c_gt[2]), num)], -1)
    out = np.tile(np.eye(4), (num, 1, 1))
    out[:, :3, :3] = R_delta @ T[:3, :3]
    out[:, :3, 3] = c_gt + d - out[:, :3, :3] @ c
    return out


def resample_mask(mask: np.ndarray, x0: float, y0: float, side: float, size: int) -> np.ndarray:
    """bool [H, W] -> bool [size, size]: nearest source pixel of each map pixel centre of the
    square crop (x0, y0, side) (pixel-edge coordinates), False outside the image."""
    h, w = mask.shape
    s = (np.arange(size) + 0.5) * (side / size) - 0.5
    cols = np.floor(x0 + s + 0.5).astype(np.int64)
    rows = np.floor(y0 + s + 0.5).astype(np.int64)
    ok = (rows >= 0) & (rows < h)
    okc = (cols >= 0) & (cols < w)
    out = mask[np.clip(rows, 0, h - 1)][:, np.clip(cols, 0, w - 1)]
    return out & ok[:, None] & okc[None, :]


# --------------------------------------------------------------------------- transform


class SampleInstance(grain.transforms.RandomMap):
    """Instance, hypotheses, crop and visible mask of one example (module docstring, step 2)."""

    def __init__(self, config: RefinerExampleConfig, table: Mapping[int, ObjectEntry],
                 spheres: Mapping[int, Sphere]):
        self.config = config
        self.banks = BankCache(table)  # the object table's entries (no bank is opened)
        self.spheres = dict(spheres)
        self.mesh_rows = {k: i for i, k in enumerate(sorted(self.spheres))}
        self.symmetries = {}

    def __getstate__(self):
        return {"config": self.config, "table": self.banks.table, "spheres": self.spheres}

    def __setstate__(self, state):
        self.__init__(state["config"], state["table"], state["spheres"])

    def _symmetries(self, obj_id: int):
        if obj_id not in self.symmetries:
            sym = bank_symmetries(self.banks.entry(obj_id).symmetries)
            self.symmetries[obj_id] = pad_symmetries(sym, self.config.max_symmetries)
        return self.symmetries[obj_id]

    def _sphere(self, obj_id: int) -> Sphere:
        try:
            return self.spheres[obj_id]
        except KeyError:
            raise KeyError(f"object {obj_id} is used by a record but has no mesh in "
                           "objects.json; re-run `python -m datagen.pack`") from None

    def random_map(self, ex, rng: np.random.Generator):
        cfg = self.config
        J, S, m = cfg.num_hypotheses, cfg.crop_size, cfg.output_size
        visib = np.asarray(ex["visib_fract"], np.float64)
        cand = np.flatnonzero(visib >= cfg.min_visib)
        K = np.asarray(ex["K"], np.float64)
        base = {"T_cam_world": np.eye(4, dtype=np.float32)[None],
                "scene_id": np.int32(ex["scene_id"]), "im_id": np.int32(ex["im_id"])}
        if cand.size == 0:
            obj_id = int(min(self.spheres))
            T = np.eye(4)
            T[2, 3] = 5.0 * self.banks.entry(obj_id).diameter
            sym, sym_mask = self._symmetries(obj_id)
            return {**base, "crops": np.zeros((1, S, S, 3), np.uint8),
                    "crop_K": K.astype(np.float32)[None],
                    "T_world_obj_gt": T.astype(np.float32),
                    "hypotheses": np.tile(T.astype(np.float32), (J, 1, 1)),
                    "visible_mask": np.zeros((1, m, m), bool), "obj_id": np.int32(obj_id),
                    "mesh_index": np.int32(self.mesh_rows[obj_id]),
                    "diameter": np.float32(self.banks.entry(obj_id).diameter),
                    "symmetries": sym, "symmetry_mask": sym_mask, "visib": np.float32(0.0),
                    "valid": np.bool_(False)}
        k = int(rng.choice(cand))
        obj_id = int(ex["obj_id"][k])
        sphere = self._sphere(obj_id)
        diameter = self.banks.entry(obj_id).diameter
        T_gt = np.asarray(ex["T_cam_obj"][k], np.float64)
        hyps = perturb_poses(T_gt, sphere.center, diameter, J, cfg, rng)
        with jax.default_device(jax.devices("cpu")[0]):
            box, crop_K = crop_frame(sphere, hyps[0], K, cfg.crop_margin, S)
        box, crop_K = np.asarray(box, np.float64), np.asarray(crop_K, np.float32)
        x0, y0 = box[0], box[1]
        side = box[2] - box[0]
        crop = warp_crop(ex["rgb"], x0, y0, side, S)
        mask = resample_mask(ex["instances"] == k + 1, x0, y0, side, m)
        sym, sym_mask = self._symmetries(obj_id)
        return {**base, "crops": crop[None], "crop_K": crop_K[None],
                "T_world_obj_gt": T_gt.astype(np.float32),
                "hypotheses": hyps.astype(np.float32), "visible_mask": mask[None],
                "obj_id": np.int32(obj_id), "mesh_index": np.int32(self.mesh_rows[obj_id]),
                "diameter": np.float32(diameter), "symmetries": sym, "symmetry_mask": sym_mask,
                "visib": np.float32(visib[k]), "valid": np.bool_(True)}


# --------------------------------------------------------------------------- dataset


def refiner_dataset(
    records_dir,
    split: str,
    config: RefinerExampleConfig,
    *,
    seed: int,
    batch_size: int | None,
    shuffle: bool = True,
    repeat: bool = True,
    process_index: int = 0,
    process_count: int = 1,
    num_records: int | None = None,
) -> grain.MapDataset:
    """The 3PT-R input pipeline over ``<records_dir>/<split>`` as a grain ``MapDataset``.

    Slicing per process, shuffling, repetition and per-element seeding as
    :func:`~threept_jax.data.detector_input.detection_dataset`; ``batch_size`` is per process
    (``None``: unbatched). The examples' ``mesh_index`` rows are those of
    ``RefinerMeshes.from_records(records_dir)``.
    """
    table = load_object_table(records_dir)
    spheres = object_spheres(records_dir)
    ds, seed = decoded_records(records_dir, split, seed=seed, shuffle=shuffle, repeat=repeat,
                               process_index=process_index, process_count=process_count,
                               num_records=num_records)
    ds = ds.random_map(SampleInstance(config, table, spheres), seed=seed + 1)
    if batch_size is not None:
        ds = ds.batch(batch_size, drop_remainder=repeat)
    return ds
