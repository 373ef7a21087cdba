"""Mitsuba 3 backend: exact ray-cast geometry outputs and a path-traced scene builder.

docs/design.md section 4. Two parts:

* :class:`MitsubaRenderer` renders one mesh, kept fixed in its object frame, for many views:
  the same outputs as the JAX rasterizer (``depth``, ``mask``, ``xyz``, ``normal``, ``rgb``,
  ``edge``, ``face_id``). Rays for all B views x H x W pixel centres are generated from K and
  ``T_cam_obj`` inside one Dr.Jit kernel and traced with ``scene.ray_intersect`` (one AOV pass,
  moving the camera, never the mesh). Casting the pixel-centre rays ourselves makes arbitrary K
  exact (fx != fy, skew, off-centre principal point) with no resampling; Mitsuba's ray
  distance is converted to z.
* :class:`MitsubaScene` builds a scene of several meshes with poses and materials (diffuse,
  plastic, rough conductor; colour, vertex colours or texture), an environment, point and
  area lights and a ground plane, and renders a path-traced ``rgb`` with ``spp`` and ``seed``
  plus the geometry outputs (depth z, instance id, object coordinates, normals) in one call:
  the data generator's renderer.

Mitsuba's perspective sensor has square pixels; for a path-traced view with fx != fy we render
square pixels at the larger focal length and resample exactly onto the requested K
(:func:`square_pixel_camera`, :func:`resample_square_render`).

Variants: ``cuda_ad_rgb`` when a CUDA device is present, else ``llvm_ad_rgb`` (needs
libLLVM >= 16; ``DRJIT_LIBLLVM_PATH`` is pointed at libLLVM-19 when it is installed). Mitsuba
is imported lazily, and its variant is process-wide (Mitsuba's own global state).

**Thread safety**: a Mitsuba scene is never shared across threads without a lock. Every
:class:`MitsubaRenderer` and :class:`MitsubaScene` holds a ``threading.Lock`` taken for each
build and render; use one instance per thread for parallel rendering.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import pathlib
import threading
from typing import Any, Sequence

import numpy as np

from threept_jax.render.mesh import DEFAULT_GREY, Mesh

_LLVM_CANDIDATES = (
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/llvm-19/lib/libLLVM-19.so",
    "/usr/lib/llvm-19/lib/libLLVM.so.19.1",
    "/usr/lib/llvm-19/lib/libLLVM.so",
    "/usr/lib/aarch64-linux-gnu/libLLVM-19.so",
)
_variant_lock = threading.Lock()
GEOMETRY_OUTPUTS = ("depth", "mask", "xyz", "normal", "rgb", "edge", "face_id")


def _find_libllvm() -> str | None:
    for p in _LLVM_CANDIDATES:
        if pathlib.Path(p).exists():
            return p
    return None


def load_mitsuba(variant: str | None = None):
    """Import Mitsuba with a working variant; returns the ``mitsuba`` module.

    ``variant`` None picks ``cuda_ad_rgb`` when Dr.Jit sees a CUDA device, else
    ``llvm_ad_rgb``. Raises with the install command when libLLVM is missing.
    """
    found = _find_libllvm()
    if found is not None:
        os.environ.setdefault("DRJIT_LIBLLVM_PATH", found)
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as e:  # pragma: no cover - dependency listed in pyproject
        raise ImportError("mitsuba is not installed: pip install 'mitsuba>=3.9.1,<3.10'") from e
    with _variant_lock:
        if variant is None:
            variant = "cuda_ad_rgb" if dr.has_backend(dr.JitBackend.CUDA) else "llvm_ad_rgb"
        if variant.startswith("llvm") and not dr.has_backend(dr.JitBackend.LLVM):
            raise RuntimeError(
                "Mitsuba's llvm variant needs libLLVM >= 16 (LLVM 14 is refused, 15 crashes): "
                "install it with `apt-get install libllvm19` (Debian/Ubuntu), or point "
                "DRJIT_LIBLLVM_PATH at an existing libLLVM-19.so"
            )
        if mi.variant() != variant:
            mi.set_variant(variant)
        if variant not in _registered_variants:
            _register_vertex_colors(mi)
            _registered_variants.add(variant)
    return mi


_registered_variants: set[str] = set()
VERTEX_COLOR_TEXTURE = "vertex_color_mean"


def _register_vertex_colors(mi) -> None:
    """Register ``vertex_color_mean``: a mesh's vertex colours as a texture that knows its mean.

    Mitsuba's own ``mesh_attribute`` texture has no ``mean()``, which ``plastic`` and
    ``roughplastic`` read to weigh sampling their specular coat against their diffuse base
    (mitsuba3 issue #1752), so a vertex-coloured part could not be plastic. This texture looks
    the colour up the same way and returns the mean we computed from the vertex colours.
    """

    class VertexColors(mi.Texture):
        def __init__(self, props):
            mi.Texture.__init__(self, props)
            self._name = props["name"]
            self._mean = float(props["mean"])

        def eval(self, si, active=True):
            return si.shape.eval_attribute_3(self._name, si, active)

        def mean(self):
            return self._mean

        def is_spatially_varying(self):
            return True

        def to_string(self):
            return f"VertexColors[{self._name}, mean={self._mean:.3f}]"

    mi.register_texture(VERTEX_COLOR_TEXTURE, lambda props: VertexColors(props))


def _opencv_to_mitsuba_camera() -> np.ndarray:
    """Mitsuba cameras look down +z with x left and y up: OpenCV axes rotated 180 deg about z."""
    return np.diag([-1.0, -1.0, 1.0, 1.0])


def square_pixel_camera(K: np.ndarray, hw: tuple[int, int]):
    """A square-pixel camera covering the view of K [3, 3] at size hw, and the crop box back.

    Returns (K_sq [3, 3], hw_sq, box [4]) with focal f = max(fx, fy), such that
    ``crop_and_resize(render_sq, box, hw)`` gives the view of K exactly (and
    ``crop_intrinsics(K_sq, box, hw) == K``). Skew is not supported by Mitsuba's sensor.
    """
    K = np.asarray(K, np.float64)
    H, W = hw
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if abs(K[0, 1]) > 1e-9:
        raise ValueError("Mitsuba's perspective sensor cannot express a skewed K (K[0, 1] != 0)")
    f = max(fx, fy)
    sx, sy = fx / f, fy / f  # crop scale: output pixels per square-render pixel
    # Square render pixel coordinates of target pixel centres: u' = (u - cx) / sx + cx';
    # choose cx' so that u' of target pixel 0 lies at 0 (plus a margin for bilinear taps).
    cxs = cx / sx + 1.0
    cys = cy / sy + 1.0
    Ws = int(math.ceil((W - 1 - cx) / sx + cxs)) + 2
    Hs = int(math.ceil((H - 1 - cy) / sy + cys)) + 2
    K_sq = np.array([[f, 0, cxs], [0, f, cys], [0, 0, 1.0]])
    # crop_intrinsics: u = (u' + 0.5 - x0) * s - 0.5  =>  x0 = u' + 0.5 - (u + 0.5) / s at u' = cx'.
    x0 = cxs + 0.5 - (cx + 0.5) / sx
    y0 = cys + 0.5 - (cy + 0.5) / sy
    box = np.array([x0, y0, x0 + W / sx, y0 + H / sy])
    return K_sq, (Hs, Ws), box


def resample_square_render(image: np.ndarray, box: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """The render of :func:`square_pixel_camera`'s K_sq [Hs, Ws, C] -> the view of K [H, W, C].

    Bilinear sampling of the crop ``box`` (pixel-edge xyxy) at the output pixels' centres, as
    :func:`threept_jax.render.crop.crop_and_resize` samples, computed by SciPy in float64 on the
    host: a data generator's bytes never depend on XLA's backend or compile options.
    """
    from scipy import ndimage

    H, W = int(hw[0]), int(hw[1])
    x0, y0, x1, y1 = (float(b) for b in box)
    sy, sx = (y1 - y0) / H, (x1 - x0) / W  # input pixels per output pixel
    # Output pixel centre i samples the input at (i + 0.5) * s + x0 - 0.5; channels map to
    # themselves.
    offset = [y0 + 0.5 * sy - 0.5, x0 + 0.5 * sx - 0.5, 0.0]
    return ndimage.affine_transform(np.asarray(image, np.float32), [sy, sx, 1.0], offset=offset,
                                    output_shape=(H, W, image.shape[-1]), order=1,
                                    mode="grid-constant", cval=0.0)


def _check_pose_k(T: np.ndarray, K: np.ndarray, what: str = "T_cam_obj") -> None:
    from threept_jax.render import check_pose_and_intrinsics

    check_pose_and_intrinsics(T, K, what)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """Linear RGB -> sRGB-encoded values in [0, 1] (IEC 61966-2-1), clipped."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def _mi_mesh(mi, mesh: Mesh, name: str, bsdf, vertices: np.ndarray | None = None, flip_uv=True):
    """A Mitsuba mesh of ``mesh`` (vertices optionally replaced, e.g. posed in the world)."""
    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = bsdf
    has_uv = mesh.uv is not None
    m = mi.Mesh(
        name,
        mesh.num_vertices,
        mesh.num_faces,
        props=props,
        has_vertex_normals=True,
        has_vertex_texcoords=has_uv,
    )
    params = mi.traverse(m)
    v = mesh.vertices if vertices is None else vertices
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(v, np.float32).ravel())
    params["faces"] = mi.UInt32(mesh.faces.astype(np.uint32).ravel())
    params["vertex_normals"] = mi.Float(mesh.normals.ravel())
    if has_uv:
        uv = mesh.uv.copy()
        if flip_uv:  # Mitsuba's bitmap puts v = 0 at the top row; our UVs are OpenGL (bottom)
            uv[:, 1] = 1.0 - uv[:, 1]
        params["vertex_texcoords"] = mi.Float(uv.ravel())
    params.update()
    if mesh.colors is not None:
        m.add_attribute("vertex_color", 3, mesh.colors.astype(np.float32).ravel().tolist())
    return m


def _albedo_texture_dict(mi, mesh: Mesh, raw: bool) -> dict:
    """The mesh's albedo as a Mitsuba texture: its image, its vertex colours, or grey."""
    if mesh.texture is not None:
        return {
            "type": "bitmap",
            "bitmap": mi.Bitmap(np.ascontiguousarray(mesh.texture.astype(np.float32) / 255.0)),
            "raw": raw,  # raw: the texture's stored values (geometry rgb); else sRGB -> linear
            "filter_type": "bilinear",
            "wrap_mode": "repeat",
        }
    if mesh.colors is not None:
        mean = float(np.mean(np.asarray(mesh.colors, np.float64)))
        return {"type": VERTEX_COLOR_TEXTURE, "name": "vertex_color", "mean": mean}
    return {"type": "rgb", "value": [DEFAULT_GREY] * 3}


class MitsubaRenderer:
    """Ray-cast geometry renders of one mesh (object frame) for batches of views.

    ``render`` matches :func:`threept_jax.render.raster.render` output for output: ``rgb`` uses
    the same headlight shading of Mitsuba's albedo (its texture / vertex colour lookup), ``edge``
    the same :func:`edges_from_geometry`. Thread safety: guarded by an instance lock.
    """

    def __init__(self, mesh: Mesh, variant: str | None = None):
        self.mi = load_mitsuba(variant)
        self.mesh = mesh
        self._lock = threading.Lock()
        mi = self.mi
        albedo = _albedo_texture_dict(mi, mesh, raw=True)
        bsdf = mi.load_dict({"type": "diffuse", "reflectance": albedo})
        self._shape = _mi_mesh(mi, mesh, "object", bsdf)
        self._scene = mi.load_dict({"type": "scene", "object": self._shape})

    def render(
        self,
        T_cam_obj: np.ndarray,
        K: np.ndarray,
        hw: tuple[int, int],
        outputs: Sequence[str] = ("depth", "mask", "xyz", "normal"),
        *,
        near: float = 1.0,
        ambient: float = 0.3,
        edge_depth_fraction: float = 0.02,
        edge_angle_deg: float = 45.0,
    ) -> dict[str, np.ndarray]:
        """Render views T_cam_obj [..., 4, 4], K [..., 3, 3] -> NumPy arrays [..., H, W, ...]."""
        outputs = tuple(dict.fromkeys(outputs))
        bad = [o for o in outputs if o not in GEOMETRY_OUTPUTS]
        if bad:
            raise ValueError(f"unknown outputs {bad}; choose from {GEOMETRY_OUTPUTS}")
        T = np.asarray(T_cam_obj, np.float64)
        lead = T.shape[:-2]
        K = np.broadcast_to(np.asarray(K, np.float64), lead + (3, 3))
        _check_pose_k(T, K)
        T, K = T.reshape(-1, 4, 4), K.reshape(-1, 3, 3)
        H, W = int(hw[0]), int(hw[1])
        with self._lock:
            with _wavefront(len(T) * H * W):
                res = _cast(self.mi, self._scene, T, K, (H, W), near, _fields(outputs))
        thr = edge_depth_fraction * self.mesh.diameter
        out = _finish(res, outputs, K, (H, W), ambient, thr, edge_angle_deg)
        return {k: v.reshape(lead + v.shape[1:]) for k, v in out.items()}


#: Renders of at most this many lanes (pixels x samples per pixel) run in Dr.Jit's wavefront
#: mode (:func:`_wavefront`); larger ones in its symbolic mode, where the path state stays in
#: registers (640 x 480 at 16 spp: 21 s and 3.6 GB wavefront against 3.2 s and 0.6 GB).
WAVEFRONT_MAX_LANES = 1 << 20


def _wavefront(lanes: int):
    """Dr.Jit's wavefront mode for a render of ``lanes`` lanes, when it is small enough
    (:data:`WAVEFRONT_MAX_LANES`); the flags are per thread, and restored.

    In its default (symbolic) mode Dr.Jit compiles a whole path tracer into one kernel that
    holds, as code and constants, every BSDF, emitter and shape alive in the process, the
    number of emitters and the film's size: every image of a data generator, with its own mix
    of parts, materials and lights, compiled a new kernel with LLVM (0.5-1.3 s each on 2 cores),
    and Dr.Jit's kernel cache (``~/.drjit``) never hit for new scenes. With virtual calls and
    loops evaluated step by step, the kernels are small and shared by every scene, and the
    renders are bit-identical to the symbolic mode's (tests/render/test_mitsuba_scene.py), so
    the choice changes speed only. Measured on 2 cores with an empty cache: the learning test's
    48 images at 160 x 128, 103-106 s -> 47.5 s; 8 demo cell images at 640 x 480, 37.3 ->
    26.4 s (docs/datagen.md, "Rendering speed"). But every step's state goes through memory,
    which large renders pay for.
    """
    import drjit as dr

    if lanes > WAVEFRONT_MAX_LANES:
        return contextlib.nullcontext()
    stack = contextlib.ExitStack()
    stack.enter_context(dr.scoped_set_flag(dr.JitFlag.SymbolicCalls, False))
    stack.enter_context(dr.scoped_set_flag(dr.JitFlag.SymbolicLoops, False))
    return stack


def _cast(mi, scene, T, K, hw, near, fields, shape_table=None):
    """Trace the pixel-centre rays of B views in one Dr.Jit kernel.

    Returns NumPy arrays [B, H, W, ...]: ``valid``, ``z`` and the requested ``fields`` among
    ``p`` (hit point, scene frame), ``n`` (shading normal, camera frame), ``ng`` (geometric
    normal, camera frame), ``prim`` (triangle index), ``albedo`` (the BSDF's diffuse
    reflectance) and ``instance`` (``shape_table`` looked up by shape).
    """
    import drjit as dr

    H, W = hw
    B = T.shape[0]
    R = T[:, :3, :3]
    t = T[:, :3, 3]
    C = -np.einsum("bji,bj->bi", R, t)  # camera centres, scene frame
    # Per view: scene-frame direction of pixel (u, v) is A [u, v, 1] with A = R^T K^-1.
    A = np.einsum("bji,bjk->bik", R, np.linalg.inv(K))
    view = np.concatenate([A.reshape(B, 9), C, R.reshape(B, 9), t], -1).astype(np.float32)
    vbuf = mi.Float(view.ravel())
    idx = dr.arange(mi.UInt32, B * H * W)
    b = idx // (H * W)
    rem = idx - b * (H * W)
    vv = rem // W
    u = mi.Float(rem - vv * W)
    v = mi.Float(vv)

    def g(k):
        return dr.gather(mi.Float, vbuf, b * 24 + k)

    def to_camera(x):
        return mi.Vector3f(*[g(12 + 3 * i) * x.x + g(13 + 3 * i) * x.y + g(14 + 3 * i) * x.z
                             for i in range(3)])

    d = mi.Vector3f(*[g(3 * i) * u + g(3 * i + 1) * v + g(3 * i + 2) for i in range(3)])
    # Start at the near plane (z = near in the camera, as K^-1 [u v 1] has z = 1): the same
    # clipping as the rasterizer.
    origin = mi.Point3f(g(9), g(10), g(11)) + d * near
    si = scene.ray_intersect(mi.Ray3f(origin, dr.normalize(d)))
    valid = si.is_valid()
    res = {"valid": valid, "z": g(18) * si.p.x + g(19) * si.p.y + g(20) * si.p.z + g(23)}
    if "p" in fields:
        res["p"] = si.p
    if "n" in fields:
        res["n"] = dr.normalize(to_camera(si.sh_frame.n))
    if "ng" in fields:
        res["ng"] = dr.normalize(to_camera(si.n))
    if "prim" in fields:
        res["prim"] = si.prim_index
    if "albedo" in fields:
        res["albedo"] = si.bsdf().eval_diffuse_reflectance(si, valid)
    if "instance" in fields:
        sid = dr.reinterpret_array(mi.UInt32, si.shape)
        res["instance"] = dr.gather(mi.UInt32, shape_table, sid, valid)
    dr.eval(*res.values())
    out = {}
    for k, val in res.items():
        a = np.array(val)
        if a.ndim == 2 and a.shape[0] == 3 and a.shape[1] == B * H * W:
            a = a.T
        out[k] = a.reshape((B, H, W) + a.shape[1:])
    return out


def _fields(outputs) -> set:
    need = set()
    need |= {"p"} if "xyz" in outputs else set()
    need |= {"n"} if {"normal", "rgb"} & set(outputs) else set()
    need |= {"albedo"} if "rgb" in outputs else set()
    need |= {"ng"} if "edge" in outputs else set()
    need |= {"prim"} if "face_id" in outputs else set()
    return need


def _camera_rays(K, hw):
    """K^-1 [u, v, 1] of every pixel centre: [B, H, W, 3] (camera frame, z = 1)."""
    H, W = hw
    uv1 = np.stack([*np.meshgrid(np.arange(W), np.arange(H)), np.ones((H, W))], -1)
    return np.einsum("bij,hwj->bhwi", np.linalg.inv(K), uv1)


def _finish(res, outputs, K, hw, ambient, depth_threshold, angle_deg):
    """The renderer's outputs from raw hits (camera frame), background zeroed."""
    from threept_jax.render.raster import edges_from_geometry

    mask = res["valid"].astype(bool)
    m3 = mask[..., None]
    out = {}
    if "mask" in outputs:
        out["mask"] = mask
    depth = np.where(mask, res["z"], 0.0).astype(np.float32)
    if "depth" in outputs:
        out["depth"] = depth
    if "xyz" in outputs:
        out["xyz"] = np.where(m3, res["p"], 0.0).astype(np.float32)
    if "face_id" in outputs:
        out["face_id"] = np.where(mask, res["prim"].astype(np.int64), -1).astype(np.int32)
    if "normal" in outputs:
        out["normal"] = np.where(m3, res["n"], 0.0).astype(np.float32)
    if "rgb" in outputs:
        ray = _camera_rays(K, hw)
        lam = np.abs((res["n"] * ray).sum(-1, keepdims=True)) / np.linalg.norm(
            ray, axis=-1, keepdims=True
        )
        rgb = np.clip(res["albedo"] * (ambient + (1 - ambient) * lam), 0, 1)
        out["rgb"] = np.where(m3, rgb, 0.0).astype(np.float32)
    if "edge" in outputs:
        pts = depth[..., None] * _camera_rays(K, hw)
        ng = np.where(m3, res["ng"], 0.0)
        out["edge"] = np.asarray(
            edges_from_geometry(mask, pts, ng, depth_threshold, angle_deg, xp=np)
        )
    return out


# --------------------------------------------------------------------------------------------
# Path-traced scenes


@dataclasses.dataclass(frozen=True)
class Material:
    """A surface for path tracing.

    kind: 'diffuse', 'plastic' (rough plastic: diffuse base with a dielectric coat) or
      'conductor' (rough metal).
    color: linear-sRGB-ish RGB in [0, 1]; None uses the mesh's texture, vertex colours or grey.
    roughness: GGX alpha of plastic and conductor.
    ior: interior index of refraction of plastic.
    """

    kind: str = "diffuse"
    color: tuple[float, float, float] | None = None
    roughness: float = 0.3
    ior: float = 1.5

    def __post_init__(self):
        if self.kind not in ("diffuse", "plastic", "conductor"):
            raise ValueError(
                f"Material.kind must be diffuse, plastic or conductor, got {self.kind!r}"
            )
        if not 0.0 < self.roughness <= 1.0:
            raise ValueError(f"Material.roughness must be in (0, 1], got {self.roughness}")

    def to_dict(self, mi, mesh: Mesh | None) -> dict:
        if self.color is not None:
            albedo = {"type": "rgb", "value": list(map(float, self.color))}
        elif mesh is not None:
            albedo = _albedo_texture_dict(mi, mesh, raw=False)
        else:
            albedo = {"type": "rgb", "value": [DEFAULT_GREY] * 3}
        if self.kind == "diffuse":
            return {"type": "diffuse", "reflectance": albedo}
        if self.kind == "plastic":
            return {
                "type": "roughplastic",
                "distribution": "ggx",
                "alpha": float(self.roughness),
                "int_ior": float(self.ior),
                "diffuse_reflectance": albedo,
            }
        return {
            "type": "roughconductor",
            "distribution": "ggx",
            "alpha": float(self.roughness),
            "specular_reflectance": albedo,
        }


def _transform(mi, T: np.ndarray):
    return mi.ScalarTransform4f(np.asarray(T, np.float64).tolist())


class MitsubaScene:
    """A scene builder for path-traced data generation (world frame, mm).

    Objects get instance ids 1, 2, ... in the order added (0 = background, ground, lights).
    The Mitsuba scene is built lazily on the first render and rebuilt after any change.
    Thread safety: guarded by an instance lock; never share a built scene across threads
    without it.
    """

    def __init__(self, variant: str | None = None, max_depth: int = 8):
        self.mi = load_mitsuba(variant)
        self.max_depth = int(max_depth)
        self._objects: list[tuple[Mesh, np.ndarray, Material]] = []
        self._lights: list[dict] = []
        self._ground: dict | None = None
        self._env: dict | None = None
        self._scene = None
        self._table = None
        self._lock = threading.Lock()

    # -- building --------------------------------------------------------------------------
    def add_object(
        self, mesh: Mesh, T_world_obj: np.ndarray, material: Material | None = None
    ) -> int:
        """Place ``mesh`` at pose T_world_obj [4, 4]; returns its instance id (1-based)."""
        T = np.asarray(T_world_obj, np.float64)
        from threept_jax.render import check_pose_and_intrinsics

        check_pose_and_intrinsics(T, None, "T_world_obj")
        with self._lock:
            self._objects.append((mesh, T, material or Material()))
            self._scene = None
            return len(self._objects)

    def set_environment(
        self,
        radiance: Sequence[float] | np.ndarray = (0.5, 0.5, 0.5),
        scale: float = 1.0,
        T_world_env: np.ndarray | None = None,
    ) -> None:
        """Environment light: a constant RGB radiance, or an equirectangular HDR image [h, w, 3]."""
        mi = self.mi
        r = np.asarray(radiance, np.float32)
        if r.ndim == 1:
            env = {"type": "constant", "radiance": {"type": "rgb", "value": (r * scale).tolist()}}
        elif r.ndim == 3 and r.shape[-1] == 3:
            env = {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(r)), "scale": scale}
            if T_world_env is not None:
                env["to_world"] = _transform(mi, T_world_env)
        else:
            raise ValueError(f"radiance must be RGB [3] or an image [h, w, 3], got {r.shape}")
        with self._lock:
            self._env = env
            self._scene = None

    def add_point_light(self, position: Sequence[float], intensity: Sequence[float]) -> None:
        """Isotropic point light at ``position`` (mm, world) with RGB ``intensity`` (W/sr)."""
        with self._lock:
            self._lights.append(
                {
                    "type": "point",
                    "position": list(map(float, position)),
                    "intensity": {"type": "rgb", "value": list(map(float, intensity))},
                }
            )
            self._scene = None

    def add_area_light(
        self, T_world_light: np.ndarray, size: tuple[float, float], radiance: Sequence[float]
    ) -> None:
        """Rectangular area light of ``size`` (w, h) mm in the xy plane of T_world_light,
        emitting toward its +z axis with RGB ``radiance``."""
        mi = self.mi
        S = np.diag([size[0] / 2, size[1] / 2, 1.0, 1.0])
        with self._lock:
            self._lights.append(
                {
                    "type": "rectangle",
                    "to_world": _transform(mi, np.asarray(T_world_light) @ S),
                    "emitter": {
                        "type": "area",
                        "radiance": {"type": "rgb", "value": list(map(float, radiance))},
                    },
                }
            )
            self._scene = None

    def set_ground(
        self,
        T_world_plane: np.ndarray | None = None,
        size: float = 2000.0,
        material: Material | None = None,
    ) -> None:
        """A square ground plane of side ``size`` mm in the xy plane of T_world_plane (default:
        the world z = 0 plane), facing +z. It is background (instance id 0)."""
        mi = self.mi
        T = np.eye(4) if T_world_plane is None else np.asarray(T_world_plane, np.float64)
        S = np.diag([size / 2, size / 2, 1.0, 1.0])
        mat = material or Material(color=(0.5, 0.5, 0.5))
        with self._lock:
            self._ground = {
                "type": "rectangle",
                "to_world": _transform(mi, T @ S),
                "bsdf": mat.to_dict(mi, None),
            }
            self._scene = None

    def set_max_depth(self, max_depth: int) -> None:
        """Path length of the path tracer (-1: unbounded); the scene is rebuilt on next render."""
        with self._lock:
            self.max_depth = int(max_depth)
            self._scene = None

    def _build(self):
        import drjit as dr

        mi = self.mi
        path = {"type": "path", "max_depth": self.max_depth}
        d: dict[str, Any] = {"type": "scene", "integrator": path}
        shapes = []
        for i, (mesh, T, mat) in enumerate(self._objects):
            bsdf = mi.load_dict(mat.to_dict(mi, mesh))
            v = mesh.vertices.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
            # Vertex normals rotate with the pose; the mesh keeps its own for shading.
            posed = dataclasses.replace(mesh, normals=mesh.normals @ T[:3, :3].T.astype(np.float32))
            shape = _mi_mesh(mi, posed, f"obj_{i + 1}", bsdf, vertices=v)
            shapes.append(shape)
            d[f"obj_{i + 1}"] = shape
        for k, light in enumerate(self._lights):
            d[f"light_{k}"] = light
        if self._ground is not None:
            d["ground"] = self._ground
        if self._env is not None:
            d["environment"] = self._env
        scene = mi.load_dict(d)
        # Instance id per pixel: Dr.Jit shape pointers are registry ids; map them to 1..N.
        def sid(shape):
            return int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0])

        size = max([sid(s) for s in scene.shapes()] + [0]) + 1  # ground and lights map to 0
        table = np.zeros(size, np.uint32)
        for i, shape in enumerate(shapes):
            table[sid(shape)] = i + 1
        self._scene, self._table = scene, mi.UInt32(table)
        # The same path tracer writing the first-hit shading normal and albedo beside the
        # colour: the auxiliary images of the denoiser. The normal comes first: in Dr.Jit's
        # wavefront mode (_wavefront) with more than one thread, a normal after the albedo lost
        # its x component on ~4 % of the pixels (a render then depended on the thread count).
        self._aov_integrator = mi.load_dict(
            {"type": "aov", "aovs": "normal:sh_normal,albedo:albedo", "integrator": path})

    # -- rendering -------------------------------------------------------------------------
    def render(
        self,
        K: np.ndarray,
        T_cam_world: np.ndarray,
        hw: tuple[int, int],
        spp: int = 64,
        seed: int = 0,
        outputs: Sequence[str] = ("rgb", "depth", "mask", "instance", "xyz", "normal"),
        near: float = 1.0,
        linear: bool = False,
        denoise: bool = False,
    ) -> dict[str, np.ndarray]:
        """Render one view K [3, 3], T_cam_world [4, 4] at hw = (H, W).

        Returns NumPy arrays: ``rgb`` [H, W, 3] path traced with ``spp`` samples (sRGB-encoded
        in [0, 1], or linear radiance with ``linear``; with ``denoise``, cleaned by Open Image
        Denoise from the same samples' albedo and normal, :mod:`threept_jax.render.denoise`),
        and, ray cast at exact pixel centres:
        ``depth`` [H, W] (z in mm of whatever is hit, ground included; 0 where rays escape),
        ``mask`` (an object is hit), ``instance`` [H, W] int32 (object id, 0 = not an object),
        ``xyz`` [H, W, 3] (coordinates in the hit object's own frame, mm; 0 off objects),
        ``normal`` [H, W, 3] (shading normal, camera frame; 0 where rays escape).
        """
        K = np.asarray(K, np.float64)
        T = np.asarray(T_cam_world, np.float64)
        _check_pose_k(T, K, "T_cam_world")
        known = {"rgb", "depth", "mask", "instance", "xyz", "normal"}
        bad = set(outputs) - known
        if bad:
            raise ValueError(f"unknown outputs {sorted(bad)}; choose from {sorted(known)}")
        if spp < 1:
            raise ValueError(f"spp must be >= 1, got {spp}")
        H, W = int(hw[0]), int(hw[1])
        with self._lock:
            if self._scene is None:
                self._build()
            out = {}
            if "rgb" in outputs:
                out["rgb"] = self._path_trace(K, T, (H, W), spp, seed, linear, denoise)
            geo = [o for o in outputs if o != "rgb"]
            if geo:
                out.update(self._geometry(K, T, (H, W), near, geo))
        return out

    def _path_trace(self, K, T, hw, spp, seed, linear, denoise):
        mi = self.mi
        H, W = hw
        exact = abs(K[0, 0] - K[1, 1]) < 1e-9 * K[0, 0]
        if exact:
            K_sq, hw_sq, box = K, hw, None
        else:
            K_sq, hw_sq, box = square_pixel_camera(K, hw)
        sensor = mi.load_dict(_sensor_dict(mi, K_sq, T, hw_sq))
        integrator = self._aov_integrator if denoise else None  # None: the scene's path tracer
        with _wavefront(hw_sq[0] * hw_sq[1] * int(spp)):
            img = np.array(mi.render(self._scene, sensor=sensor, integrator=integrator,
                                     spp=int(spp), seed=int(seed)), np.float32)
        if denoise:  # channels: colour, then the AOVs in the order named in _build (normal, albedo)
            from threept_jax.render.denoise import denoise as oidn

            img = oidn(img[..., 0:3], img[..., 6:9], img[..., 3:6])
        img = img[..., :3]
        if box is not None:
            img = resample_square_render(img, box, hw)
        return img if linear else linear_to_srgb(img).astype(np.float32)

    def _geometry(self, K, T, hw, near, outputs):
        fields = {"instance"} | ({"p"} if "xyz" in outputs else set())
        fields |= {"n"} if "normal" in outputs else set()
        with _wavefront(hw[0] * hw[1]):
            res = _cast(self.mi, self._scene, T[None], K[None], hw, near, fields, self._table)
        inst = np.where(res["valid"], res["instance"], 0).astype(np.int32)[0]
        hit = inst > 0
        out = {}
        if "instance" in outputs:
            out["instance"] = inst
        if "mask" in outputs:
            out["mask"] = hit
        valid = res["valid"][0].astype(bool)
        if "depth" in outputs:  # the whole scene: objects, ground, light geometry
            out["depth"] = np.where(valid, res["z"][0], 0.0).astype(np.float32)
        if "xyz" in outputs:
            # World -> object frame of the instance hit at each pixel (identity for 0).
            poses = np.stack([np.eye(4)] + [o[1] for o in self._objects])
            Ti = np.linalg.inv(poses)[inst]  # [H, W, 4, 4]
            xyz = np.einsum("hwij,hwj->hwi", Ti[..., :3, :3], res["p"][0]) + Ti[..., :3, 3]
            out["xyz"] = np.where(hit[..., None], xyz, 0.0).astype(np.float32)
        if "normal" in outputs:
            out["normal"] = np.where(valid[..., None], res["n"][0], 0.0).astype(np.float32)
        return out


def _sensor_dict(mi, K: np.ndarray, T_cam_world: np.ndarray, hw) -> dict:
    """Mitsuba perspective sensor for a square-pixel K (OpenCV camera T_cam_world)."""
    H, W = hw
    f, cx, cy = K[0, 0], K[0, 2], K[1, 2]
    fov = math.degrees(2.0 * math.atan(W / (2.0 * f)))
    T_world_cam = np.linalg.inv(T_cam_world) @ _opencv_to_mitsuba_camera()
    return {
        "type": "perspective",
        "fov_axis": "x",
        "fov": fov,
        # Offsets of the film centre from the principal point, in film widths / heights (the
        # sign Mitsuba uses; tested); the film coordinate of OpenCV pixel centre u is u + 0.5.
        "principal_point_offset_x": (W / 2.0 - cx - 0.5) / W,
        "principal_point_offset_y": (H / 2.0 - cy - 0.5) / H,
        "near_clip": 1.0,
        "far_clip": 1e7,
        "to_world": _transform(mi, T_world_cam),
        "film": {
            "type": "hdrfilm",
            "width": int(W),
            "height": int(H),
            # The box filter accumulates samples in a fixed order, so a render is bit-identical
            # for a seed (datagen's determinism); the default Gaussian filter splats with atomic
            # adds in thread order (1e-7 differences that flip uint8 roundings). Random
            # sub-pixel sample positions still antialias.
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
        },
        "sampler": {"type": "independent"},
    }


class MeshRenderError(ValueError):
    """A mesh that loads but that the path tracer cannot render (the message names the cause)."""


def check_renders(mesh: Mesh, variant: str | None = None) -> None:
    """Path-trace ``mesh`` once in every :class:`Material` kind with its own colours or texture.

    A tiny view (16 x 16 px, 1 sample): what fails here is the mesh's data meeting Mitsuba
    (an attribute a BSDF cannot read, a texture it cannot load), not the image. Raises
    :class:`MeshRenderError` with Mitsuba's one-line cause.
    """
    scene = MitsubaScene(variant, max_depth=3)
    r = 0.5 * float(mesh.diameter or np.ptp(mesh.vertices, axis=0).max())
    kinds = ("diffuse", "plastic", "conductor")
    for i, kind in enumerate(kinds):
        T = np.eye(4)
        T[0, 3] = (i - 1) * 2.5 * r
        scene.add_object(mesh, T, Material(kind))
    scene.set_environment((0.8, 0.8, 0.8))
    f = 16.0
    K = np.array([[f, 0, 8.0], [0, f, 8.0], [0, 0, 1]])
    T_cam_world = np.eye(4)
    T_cam_world[2, 3] = 8.0 * r * len(kinds)
    try:
        out = scene.render(K, T_cam_world, (16, 16), spp=1, outputs=("rgb",))
    except RuntimeError as e:
        cause = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
        raise MeshRenderError(f"does not render in Mitsuba: {cause}") from e
    if not np.isfinite(out["rgb"]).all():
        raise MeshRenderError("renders NaN or infinite colours in Mitsuba (check its normals, "
                              "UVs and colours for NaN)")
