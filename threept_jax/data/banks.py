"""Render banks: the per-object renders 3PT-D's object tower consumes, and the object table.

A :class:`RenderBank` holds, for one object (docs/design.md section 1.1):

===================  ====================  ==================================================
field                dtype, shape          meaning
===================  ====================  ==================================================
obj_id               int                   key of the object table
prior_rgb            uint8 [12, h, w, 3]   renders at ``grids.prior_view_rotations()``
prior_rotations      float32 [12, 3, 3]    R_cam_obj of each prior render
template_rgb         uint8 [T, h, w, 3]    renders at ``grids.super_fibonacci_rotations(T)``
template_rotations   float32 [T, 3, 3]     R_cam_obj of each template render
symmetries           float32 [S, 4, 4]     symmetry transforms, identity first (BOP)
diameter             float                 model diameter, mm
center               float32 [3]           centre of the bounding sphere, object frame, mm
radius               float                 radius of the bounding sphere, mm
===================  ====================  ==================================================

**The render camera** (every render of a bank, priors and templates alike). Each render is an
object-centred view: a pinhole camera looks at the bounding-sphere centre ``c`` from
``distance = DISTANCE_FACTOR * radius`` along its optical axis, so the object pose is
``T_cam_obj = [R | (0, 0, distance) - R c]`` (:func:`render_pose`). The focal length makes
the sphere's silhouette span ``FILL`` (90 %) of the image side: a sphere of radius r at
distance d seen on the optical axis is a cone of half-angle ``a = asin(r / d)`` whose image is
a disc of radius ``f tan(a)`` pixels, so ``f = FILL * (side / 2) / tan(a)`` with
``side = min(h, w)``, and the principal point is the image centre ``((w - 1) / 2, (h - 1) / 2)``
(pixel-centre convention, :mod:`threept_jax.geometry.camera`). :func:`render_camera` returns
K and the distance. With ``DISTANCE_FACTOR = 4`` the perspective is that of an object seen
from four times its radius (a = 14.5 degrees; f = 1.74 * side).

**Rotations of off-axis objects.** A template shows the object as seen by a camera looking
straight at its centre. An object off the optical axis of a real camera is seen along the ray
through its centre, so the template that matches its appearance is the one at ``R_ray^T
R_cam_obj`` (:func:`threept_jax.geometry.camera.object_centred_rotation`), where ``R_ray`` is
the smallest rotation that takes the optical axis (z) onto that ray: the object's rotation in a
virtual camera with the same centre, turned to look at the object (its image axes stay as close
to the real camera's as the turn allows). Inference goes back with
:func:`threept_jax.geometry.camera.camera_rotation` along the same ray, through the sphere
centre of the pose it fits to the detected box
(:func:`threept_jax.pipeline.object_generation.pose_from_box`). What remains is the perspective
warp between the real image around the object and the virtual camera's view: the real image
plane is tilted by the off-axis angle theta against the virtual one, so the object appears
stretched by 1 / cos(theta) along the radial direction (4 %
at 16 degrees off-axis, 15 % at 30 degrees).

**On disk** a bank is one ``.npz`` (no pickle), written atomically: the images are PNG (or
JPEG) encoded one by one and concatenated into a byte array with offsets, so
:class:`BankFile` can decode any subset of templates without reading the others (the 5140
templates of the paper are ~10^3 times more than a training example needs).

**Object table** (``objects.json`` of a records folder, :func:`load_object_table`)::

    {"<obj_id>": {"name": str, "diameter": mm, "bank": "banks/obj_000001.npz",
                  "split": "train" | "val" (optional),
                  "symmetries_discrete": [[16 floats], ...] (optional, BOP),
                  "symmetries_continuous": [{"axis": [3], "offset": [3]}, ...] (optional)}}

Shapes: T templates, S symmetries, h w render size.
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import pathlib
import zipfile
from typing import Any

import cv2
import numpy as np

from threept_jax.data.files import atomic_write_bytes, atomic_write_json
from threept_jax.data.records import NPY_HEADER_LOCK
from threept_jax.geometry.diameter import MIN_DIAMETER_MM
from threept_jax.geometry.symmetry import Symmetries, symmetry_transforms

BANK_FORMAT_VERSION = 1
#: Default render side (pixels) and template count of the banks datagen writes; the side must
#: equal the detector's ``render_size`` (tiny 32, small 112, paper 224: ``check_render_size``);
#: 5140 templates is the paper's bank (``grids.NUM_TEMPLATES``).
BANK_SIZE = 96
BANK_TEMPLATES = 5140

#: Share of the render's side that the bounding sphere's silhouette spans.
FILL = 0.9
#: Camera distance of a render, in bounding-sphere radii.
DISTANCE_FACTOR = 4.0
#: Discretisation step (radians) of continuous symmetries in banks. BOP evaluation uses 0.01
#: (315 rotations per axis); the template grid of the paper has a 12.8-degree covering radius,
#: so a 0.05 step (63 rotations, 5.7 degrees apart) already resolves it.
BANK_SYM_DISC_STEP = 0.05

__all__ = [
    "BANK_FORMAT_VERSION", "BANK_SYM_DISC_STEP", "BankFile", "DISTANCE_FACTOR", "FILL",
    "ObjectEntry", "RenderBank", "bank_symmetries", "bounding_sphere", "check_render_size",
    "load_bank", "load_object_table",
    "render_camera", "render_pose", "save_bank", "write_object_table",
]


# --------------------------------------------------------------------------- render camera


def render_camera(image_hw: tuple[int, int], radius: float, fill: float = FILL,
                  distance_factor: float = DISTANCE_FACTOR) -> tuple[np.ndarray, float]:
    """K [3, 3] float64 and camera distance (mm) of a bank render (module docstring)."""
    h, w = (int(v) for v in image_hw)
    if h < 1 or w < 1:
        raise ValueError(f"render size must be positive, got {image_hw}")
    if not radius > 0:
        raise ValueError(f"bounding-sphere radius must be > 0 mm, got {radius}")
    if not 0 < fill <= 1 or not distance_factor > 1:
        raise ValueError(f"need 0 < fill <= 1 and distance_factor > 1, got {fill}, "
                         f"{distance_factor}")
    half_angle = np.arcsin(1.0 / distance_factor)
    f = fill * (min(h, w) / 2.0) / np.tan(half_angle)
    K = np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
    return K, float(distance_factor * radius)


def render_pose(rotations: np.ndarray, center: np.ndarray, distance: float) -> np.ndarray:
    """T_cam_obj [..., 4, 4] of renders at rotations [..., 3, 3] looking at ``center`` [3]."""
    R = np.asarray(rotations, np.float64)
    c = np.asarray(center, np.float64).reshape(3)
    T = np.zeros((*R.shape[:-2], 4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = np.array([0.0, 0.0, distance]) - R @ c
    T[..., 3, 3] = 1.0
    return T


def bounding_sphere(vertices: np.ndarray) -> tuple[np.ndarray, float]:
    """(centre [3], radius) of a bounding sphere of vertices [N, 3] (mm).

    The centre is the centre of the axis-aligned 3D box (as in BOP's models_info) and the
    radius the largest vertex distance from it: not the minimal sphere, but every vertex is
    inside and the centre is what BOP tools call the model centre.
    """
    v = np.asarray(vertices, np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise ValueError(f"vertices must be [N, 3] with N >= 1, got {v.shape}")
    c = (v.min(0) + v.max(0)) / 2.0
    return c, float(np.linalg.norm(v - c, axis=1).max())


def check_render_size(images: np.ndarray, size: int | None, where: str) -> np.ndarray:
    """``images`` uint8 [N, h, w, 3] when h = w = ``size`` (``None``: any size); raises
    otherwise. Banks are rendered at the detector's render size and never resized, so training
    and inference onboarding see the same images (``threept_jax.pipeline.onboarding``)."""
    if size is None or images.shape[1:3] == (size, size):
        return images
    raise ValueError(
        f"{where} holds {images.shape[1]}x{images.shape[2]} renders but the detector's "
        f"render_size is {size}; banks are rendered at the model's render size (the size and "
        f"anti-aliasing inference onboarding uses): re-render them with `python -m datagen.banks "
        f"--records DIR --size {size} --force` (or pack with --bank-size {size})")


def bank_symmetries(symmetries: Symmetries, max_sym_disc_step: float = BANK_SYM_DISC_STEP
                    ) -> np.ndarray:
    """[S, 4, 4] float32 symmetry transforms of a bank, identity first (BOP construction,
    :func:`threept_jax.geometry.symmetry.symmetry_transforms`, with the bank's coarser step)."""
    R, t = symmetry_transforms(symmetries, max_sym_disc_step)
    out = np.zeros((len(R), 4, 4), np.float32)
    out[:, :3, :3] = R
    out[:, :3, 3] = t
    out[:, 3, 3] = 1.0
    return out


# --------------------------------------------------------------------------- the bank record


def _check_images(name: str, images: np.ndarray, n: int | None = None) -> np.ndarray:
    images = np.asarray(images)
    if images.dtype != np.uint8 or images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(f"{name} must be uint8 [N, h, w, 3], got {images.dtype} {images.shape}")
    if n is not None and len(images) != n:
        raise ValueError(f"{name} has {len(images)} images, expected {n}")
    return images


def _check_rotations(name: str, R: np.ndarray, n: int) -> np.ndarray:
    R = np.asarray(R, np.float32)
    if R.shape != (n, 3, 3):
        raise ValueError(f"{name} must be [{n}, 3, 3], got {R.shape}")
    err = np.abs(np.einsum("nji,njk->nik", R.astype(np.float64), R) - np.eye(3)).max(initial=0)
    if err > 1e-3:
        raise ValueError(f"{name} are not rotation matrices (|R^T R - I| = {err:.2g})")
    return R


@dataclasses.dataclass(frozen=True, eq=False)
class RenderBank:
    """One object's prior and template renders (module table). Arrays are read-only."""

    obj_id: int
    prior_rgb: np.ndarray
    prior_rotations: np.ndarray
    template_rgb: np.ndarray
    template_rotations: np.ndarray
    symmetries: np.ndarray
    diameter: float
    center: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3, np.float32))
    radius: float | None = None

    def __post_init__(self):
        prior = _check_images("prior_rgb", self.prior_rgb)
        tmpl = _check_images("template_rgb", self.template_rgb)
        if prior.shape[1:] != tmpl.shape[1:]:
            raise ValueError(f"prior renders {prior.shape[1:3]} and template renders "
                             f"{tmpl.shape[1:3]} must have the same size")
        sym = np.asarray(self.symmetries, np.float32)
        if sym.ndim != 3 or sym.shape[1:] != (4, 4) or len(sym) < 1:
            raise ValueError(f"symmetries must be [S >= 1, 4, 4] (identity first), got "
                             f"{sym.shape}")
        if np.abs(sym[0] - np.eye(4)).max() > 1e-6:
            raise ValueError("symmetries[0] must be the identity (BOP symmetry_transforms order); "
                             "build them with threept_jax.data.banks.bank_symmetries")
        if not self.diameter > 0:
            raise ValueError(f"diameter must be > 0 mm, got {self.diameter}")
        radius = self.diameter / 2.0 if self.radius is None else float(self.radius)
        fields = {
            "obj_id": int(self.obj_id),
            "prior_rgb": prior,
            "prior_rotations": _check_rotations("prior_rotations", self.prior_rotations,
                                                len(prior)),
            "template_rgb": tmpl,
            "template_rotations": _check_rotations("template_rotations",
                                                   self.template_rotations, len(tmpl)),
            "symmetries": sym,
            "diameter": float(self.diameter),
            "center": np.asarray(self.center, np.float32).reshape(3),
            "radius": radius,
        }
        for k, v in fields.items():
            if isinstance(v, np.ndarray):
                v = v.copy()
                v.setflags(write=False)
            object.__setattr__(self, k, v)

    @property
    def num_templates(self) -> int:
        return len(self.template_rgb)

    @property
    def image_hw(self) -> tuple[int, int]:
        return tuple(self.template_rgb.shape[1:3])

    def camera(self) -> tuple[np.ndarray, float]:
        """K [3, 3] and distance (mm) of this bank's renders (:func:`render_camera`)."""
        return render_camera(self.image_hw, self.radius)


def _encode_images(images: np.ndarray, image_format: str) -> tuple[np.ndarray, np.ndarray]:
    chunks, offsets = [], [0]
    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if image_format == "jpg" else []
    for im in images:
        ok, buf = cv2.imencode("." + image_format, cv2.cvtColor(im, cv2.COLOR_RGB2BGR), params)
        if not ok:
            raise RuntimeError("OpenCV failed to encode a bank render")
        chunks.append(buf.reshape(-1))
        offsets.append(offsets[-1] + buf.size)
    data = np.concatenate(chunks) if chunks else np.zeros(0, np.uint8)
    return data.astype(np.uint8), np.asarray(offsets, np.int64)


def _decode_image(buf: np.ndarray) -> np.ndarray:
    bgr = cv2.imdecode(np.asarray(buf), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError("a bank render could not be decoded; the bank file is corrupt "
                         "(re-render it with the data generator)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def save_bank(path, bank: RenderBank, image_format: str = "png") -> None:
    """Write ``bank`` to ``path`` (.npz, no pickle) through a temporary file and a rename."""
    if image_format not in ("png", "jpg"):
        raise ValueError(f"image_format must be 'png' or 'jpg', got {image_format!r}")
    path = pathlib.Path(path)
    prior_data, prior_offsets = _encode_images(bank.prior_rgb, image_format)
    tmpl_data, tmpl_offsets = _encode_images(bank.template_rgb, image_format)
    buf = io.BytesIO()
    # Stored, not deflated: the images are already compressed, and stored members can be
    # memory-mapped (BankFile).
    np.savez(
        buf,
        version=np.int32(BANK_FORMAT_VERSION),
        obj_id=np.int64(bank.obj_id),
        diameter=np.float64(bank.diameter),
        center=bank.center,
        radius=np.float64(bank.radius),
        image_hw=np.asarray(bank.image_hw, np.int64),
        prior_rotations=bank.prior_rotations,
        template_rotations=bank.template_rotations,
        symmetries=bank.symmetries,
        prior_data=prior_data,
        prior_offsets=prior_offsets,
        template_data=tmpl_data,
        template_offsets=tmpl_offsets,
    )
    atomic_write_bytes(path, buf.getvalue())


def _npz_member_memmap(path: pathlib.Path, name: str) -> np.ndarray:
    """Memory-map the array ``name`` of an uncompressed .npz (read-only)."""
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo(name + ".npy")
        if info.compress_type != zipfile.ZIP_STORED:
            raise ValueError(f"{path}: member {name} is compressed; write banks with save_bank")
    with open(path, "rb") as f:
        f.seek(info.header_offset)
        local = f.read(30)
        if local[:4] != b"PK\x03\x04":
            raise ValueError(f"{path} is not a valid .npz (bad local header of {name})")
        name_len = int.from_bytes(local[26:28], "little")
        extra_len = int.from_bytes(local[28:30], "little")
        f.seek(info.header_offset + 30 + name_len + extra_len)
        version = np.lib.format.read_magic(f)
        read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                       else np.lib.format.read_array_header_2_0)
        with NPY_HEADER_LOCK:
            shape, fortran, dtype = read_header(f)
        offset = f.tell()
    if fortran or len(shape) != 1:
        raise ValueError(f"{path}: member {name} must be a 1-D C-ordered array")
    if shape[0] == 0:
        return np.zeros(0, dtype)
    return np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=shape)


class BankFile:
    """Lazy reader of a bank file: metadata at open, renders decoded on demand.

    ``templates(indices)`` and ``priors()`` decode only the requested images from a
    memory-mapped byte array. Not picklable state is opened lazily, so a ``BankFile`` can be
    created in one process and used in another (grain workers).
    """

    def __init__(self, path):
        self.path = pathlib.Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(
                f"render bank {self.path} is missing; the object table points to it "
                "(generate banks with `python -m datagen.generate`)")
        if not zipfile.is_zipfile(self.path):
            raise ValueError(f"{self.path} is not a render bank written by save_bank (not an "
                             ".npz archive); re-render it")
        try:
            with NPY_HEADER_LOCK, np.load(self.path, allow_pickle=False) as z:
                version = int(z["version"])
                if version != BANK_FORMAT_VERSION:
                    raise ValueError(
                        f"{self.path}: bank format version {version}, this code reads "
                        f"{BANK_FORMAT_VERSION}; re-render the banks with the data generator")
                self.obj_id = int(z["obj_id"])
                self.diameter = float(z["diameter"])
                self.center = z["center"].astype(np.float32)
                self.radius = float(z["radius"])
                self.image_hw = tuple(int(v) for v in z["image_hw"])
                self.prior_rotations = z["prior_rotations"].astype(np.float32)
                self.template_rotations = z["template_rotations"].astype(np.float32)
                self.symmetries = z["symmetries"].astype(np.float32)
                self._prior_offsets = z["prior_offsets"]
                self._template_offsets = z["template_offsets"]
        except (zipfile.BadZipFile, KeyError, EOFError) as e:
            raise ValueError(f"{self.path} is not a render bank written by save_bank ({e}); "
                             "re-render it") from e
        self._data: dict[str, np.ndarray] = {}

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_data"] = {}
        return state

    @property
    def num_templates(self) -> int:
        return len(self.template_rotations)

    def _member(self, name: str) -> np.ndarray:
        if name not in self._data:
            self._data[name] = _npz_member_memmap(self.path, name)
        return self._data[name]

    def _decode(self, kind: str, indices) -> np.ndarray:
        data = self._member(f"{kind}_data")
        offsets = self._prior_offsets if kind == "prior" else self._template_offsets
        indices = np.asarray(indices, np.int64).reshape(-1)
        n = len(offsets) - 1
        if indices.size and (indices.min() < 0 or indices.max() >= n):
            raise IndexError(f"{self.path}: {kind} index out of range [0, {n})")
        if indices.size == 0:
            return np.zeros((0, *self.image_hw, 3), np.uint8)
        return np.stack([_decode_image(data[offsets[i]:offsets[i + 1]]) for i in indices])

    def priors(self) -> np.ndarray:
        """uint8 [12, h, w, 3] prior renders."""
        return self._decode("prior", np.arange(len(self.prior_rotations)))

    def templates(self, indices) -> np.ndarray:
        """uint8 [n, h, w, 3] template renders ``indices`` [n]."""
        return self._decode("template", indices)

    def load(self) -> RenderBank:
        """Decode everything into a :class:`RenderBank`."""
        return RenderBank(
            obj_id=self.obj_id, prior_rgb=self.priors(), prior_rotations=self.prior_rotations,
            template_rgb=self.templates(np.arange(self.num_templates)),
            template_rotations=self.template_rotations, symmetries=self.symmetries,
            diameter=self.diameter, center=self.center, radius=self.radius)


def load_bank(path) -> RenderBank:
    """Read a bank written by :func:`save_bank` (all renders decoded)."""
    return BankFile(path).load()


# --------------------------------------------------------------------------- object table


@dataclasses.dataclass(frozen=True, eq=False)
class ObjectEntry:
    """One row of ``objects.json``: id, name, diameter (mm), BOP symmetries, bank path
    (absolute) and split (``None`` when the table gives none)."""

    obj_id: int
    name: str
    diameter: float
    symmetries: Symmetries
    bank_path: pathlib.Path
    split: str | None = None


def _parse_entry(obj_id: int, raw: Any, path: pathlib.Path) -> ObjectEntry:
    where = f"{path} object {obj_id}"
    if not isinstance(raw, dict):
        raise ValueError(f"{where}: entry must be an object with name, diameter and bank")
    missing = [k for k in ("diameter", "bank") if k not in raw]
    if missing:
        raise ValueError(f"{where}: missing {missing}; see threept_jax.data.banks for the format")
    diameter = float(raw["diameter"])
    if not diameter >= MIN_DIAMETER_MM:
        raise ValueError(f"{where}: diameter {diameter} looks like metres; the object table is "
                         "in millimetres")
    split = raw.get("split")
    if split is not None and not isinstance(split, str):
        raise ValueError(f"{where}: split must be a string such as 'train' or 'val'")
    return ObjectEntry(
        obj_id=obj_id, name=str(raw.get("name", f"obj_{obj_id:06d}")), diameter=diameter,
        symmetries=Symmetries.from_json(raw, where),
        bank_path=(path.parent / raw["bank"]).resolve(), split=split)


def load_object_table(records_dir) -> dict[int, ObjectEntry]:
    """Read ``<records_dir>/objects.json`` -> {obj_id: ObjectEntry} (module docstring)."""
    path = pathlib.Path(records_dir) / "objects.json"
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} is missing: a records folder needs an object table (objects.json, written "
            "by `python -m datagen.pack`)")
    try:
        raw = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path} is not valid JSON ({e}); the file is probably truncated") from e
    if not isinstance(raw, dict) or not raw:
        raise ValueError(f"{path} must map object ids to entries and list at least one object")
    table = {}
    for key, entry in raw.items():
        try:
            obj_id = int(key)
        except ValueError:
            raise ValueError(f"{path}: key {key!r} is not an integer object id") from None
        table[obj_id] = _parse_entry(obj_id, entry, path)
    return dict(sorted(table.items()))


def write_object_table(records_dir, entries) -> None:
    """Write ``objects.json`` for ObjectEntry rows (bank paths relative to ``records_dir``)."""
    records_dir = pathlib.Path(records_dir).resolve()
    out = {}
    for e in entries:
        row = {"name": e.name, "diameter": float(e.diameter),
               "bank": os.path.relpath(pathlib.Path(e.bank_path).resolve(), records_dir)}
        if e.split is not None:
            row["split"] = e.split
        row.update(e.symmetries.to_json())
        out[str(int(e.obj_id))] = row
    atomic_write_json(records_dir / "objects.json", out, indent=1)
