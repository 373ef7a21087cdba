"""Appearance of synthetic scenes: materials, procedural textures, skies and support surfaces.

3PT's detector and refiner are trained on path-traced images whose objects must not be
recognisable by their colour or texture (the CAD meshes are untextured; docs/design.md
section 1), so every instance gets a random material:

* kinds: ``diffuse``, ``plastic`` (rough plastic: diffuse base under a dielectric coat) and
  ``conductor`` (rough metal), the three ``threept_jax.render.mitsuba_backend.Material`` kinds;
* albedo: a random colour, or a procedural texture (``noise``, ``stripes``, ``checker``,
  ``scratches``) wrapped onto the mesh by box projection (:func:`box_uv_mesh`), or the mesh's own
  texture / vertex colours when it has them.

Backgrounds reuse the same textures on a large ground quad, on bin walls and on far backdrop
walls. The environment is a procedural HDR sky (:func:`sky_environment`: gradient, a sun and
soft window lights; nothing is downloaded).

Every function is a deterministic function of the ``np.random.Generator`` passed in. Textures
are periodic (they tile without seams): noise is filtered white noise in the Fourier domain,
stripes have whole periods across the tile, checkers a whole number of cells and scratches wrap
around the edges. Colours are drawn in sRGB and converted to linear RGB where Mitsuba expects
linear values (``Material.color``); textures stay sRGB (Mitsuba linearises bitmaps).
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from threept_jax.render.mesh import Mesh
from threept_jax.render.mitsuba_backend import Material, linear_to_srgb

TEXTURE_KINDS = ("noise", "stripes", "checker", "scratches")
MATERIAL_KINDS = ("diffuse", "plastic", "conductor")

# Base colours (sRGB) of common metals: steel, aluminium, brass, copper, dark oxide, zinc.
_METAL_COLORS = np.array(
    [
        [0.78, 0.78, 0.80],
        [0.91, 0.92, 0.92],
        [0.89, 0.78, 0.50],
        [0.95, 0.64, 0.54],
        [0.35, 0.35, 0.37],
        [0.80, 0.82, 0.85],
    ]
)


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB values in [0, 1] -> linear RGB (IEC 61966-2-1)."""
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def random_color(rng: np.random.Generator, metal: bool = False) -> np.ndarray:
    """sRGB colour [3] in [0, 1]: any hue (HSV with a bias to industrial greys), or a metal."""
    if metal:
        base = _METAL_COLORS[int(rng.integers(len(_METAL_COLORS)))]
        return np.clip(base * rng.uniform(0.85, 1.05) + rng.normal(0, 0.02, 3), 0.02, 1.0)
    h = rng.uniform(0, 360)
    # A third of the colours are near-neutral (machined, painted and anodised parts).
    s = rng.uniform(0.0, 0.15) if rng.random() < 0.33 else rng.uniform(0.2, 0.95)
    v = rng.uniform(0.12, 0.95)
    hsv = np.array([[[h / 2, s * 255, v * 255]]], np.float32)  # OpenCV: H in [0, 180)
    rgb = cv2.cvtColor(hsv.astype(np.uint8), cv2.COLOR_HSV2RGB)[0, 0] / 255.0
    return rgb.astype(np.float64)


# --------------------------------------------------------------------------------------------
# Periodic procedural textures (uint8 [N, N, 3] sRGB).


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Per-pixel blend of sRGB colours a, b [3] by t [N, N] in [0, 1] -> uint8 [N, N, 3]."""
    out = a[None, None] * (1 - t[..., None]) + b[None, None] * t[..., None]
    return np.clip(np.round(out * 255), 0, 255).astype(np.uint8)


def _fractal_noise(rng: np.random.Generator, size: int, beta: float) -> np.ndarray:
    """Periodic 1/f^beta noise [size, size] in [0, 1] (white noise filtered by FFT)."""
    white = rng.normal(size=(size, size))
    f = np.fft.fftfreq(size)
    r = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    r[0, 0] = 1.0
    amp = r ** (-beta / 2)
    amp[0, 0] = 0.0
    x = np.real(np.fft.ifft2(np.fft.fft2(white) * amp))
    lo, hi = np.percentile(x, [1, 99])
    return np.clip((x - lo) / max(hi - lo, 1e-12), 0.0, 1.0)


def noise_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Cloudy or grainy noise between two colours (cast iron, concrete, painted surfaces)."""
    a, b = random_color(rng), random_color(rng)
    t = _fractal_noise(rng, size, beta=rng.uniform(1.5, 3.5))
    return _mix(a, b, t)


def stripes_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Straight stripes (whole periods across the tile, so it repeats seamlessly)."""
    a, b = random_color(rng), random_color(rng)
    kx, ky = 0, 0
    while kx == 0 and ky == 0:
        kx, ky = (int(k) for k in rng.integers(-8, 9, 2))
    y, x = np.mgrid[0:size, 0:size] / size
    phase = 2 * np.pi * (kx * x + ky * y)
    sharp = rng.uniform(1.0, 12.0)  # 1: soft sine bands, 12: near-hard edges
    t = 0.5 + 0.5 * np.tanh(sharp * np.sin(phase)) / np.tanh(sharp)
    return _mix(a, b, t)


def checker_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Checkerboard with a whole number of cells per tile."""
    a, b = random_color(rng), random_color(rng)
    divisors = [d for d in (2, 4, 8, 16, 32) if size % d == 0]
    n = divisors[int(rng.integers(len(divisors)))]
    y, x = np.mgrid[0:size, 0:size] * n // size
    return _mix(a, b, ((x + y) % 2).astype(np.float64))


def scratches_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Brushed / scratched surface: a base colour with faint grain and many thin lines."""
    base = random_color(rng, metal=rng.random() < 0.6)
    grain = _fractal_noise(rng, size, beta=rng.uniform(0.5, 1.5))
    img = base[None, None] * (1.0 + 0.08 * (grain[..., None] - 0.5))
    lines = np.zeros((size, size), np.float32)
    direction = rng.uniform(0, np.pi)
    spread = rng.choice([0.15, np.pi])  # brushed (mostly parallel) or random scratches
    for _ in range(int(rng.integers(40, 200))):
        x0, y0 = rng.uniform(0, size, 2)
        ang = direction + rng.uniform(-spread, spread)
        length = rng.uniform(0.05, 0.6) * size
        x1, y1 = x0 + length * math.cos(ang), y0 + length * math.sin(ang)
        value = float(rng.uniform(0.3, 1.0))
        # Draw shifted copies so that lines leaving the tile re-enter on the other side.
        for dx in (-size, 0, size):
            for dy in (-size, 0, size):
                p0 = (int(round(x0 + dx)), int(round(y0 + dy)))
                p1 = (int(round(x1 + dx)), int(round(y1 + dy)))
                cv2.line(lines, p0, p1, value, 1, cv2.LINE_8)
    sign = 1.0 if rng.random() < 0.7 else -1.0
    img = img * (1.0 + sign * 0.25 * lines[..., None])
    return np.clip(np.round(img * 255), 0, 255).astype(np.uint8)


_TEXTURES = {
    "noise": noise_texture,
    "stripes": stripes_texture,
    "checker": checker_texture,
    "scratches": scratches_texture,
}


def random_texture(rng: np.random.Generator, size: int = 256, kind: str | None = None):
    """(kind, uint8 [size, size, 3]) of a random procedural texture (``TEXTURE_KINDS``)."""
    if kind is None:
        kind = TEXTURE_KINDS[int(rng.integers(len(TEXTURE_KINDS)))]
    if kind not in _TEXTURES:
        raise ValueError(f"unknown texture kind {kind!r}; choose from {TEXTURE_KINDS}")
    return kind, _TEXTURES[kind](rng, size)


# --------------------------------------------------------------------------------------------
# Appearance of one instance.


@dataclasses.dataclass(frozen=True, eq=False)
class Appearance:
    """How one instance looks.

    Attributes:
      material: the Mitsuba material (``color`` None means: use the mesh's texture or colours).
      texture: uint8 [N, N, 3] procedural texture to wrap onto the mesh, or None.
      texture_mm: side of one texture tile on the surface, mm.
      label: short description for the scene log, e.g. ``"plastic/stripes"``.
    """

    material: Material
    texture: np.ndarray | None = None
    texture_mm: float = 100.0
    label: str = ""


def random_appearance(
    rng: np.random.Generator,
    diameter: float,
    *,
    has_own_appearance: bool = False,
    own_probability: float = 0.5,
    texture_probability: float = 0.35,
    texture_size: int = 256,
) -> Appearance:
    """A random material for an object of ``diameter`` mm.

    Meshes with their own texture or vertex colours keep them with ``own_probability``;
    otherwise the albedo is a procedural texture (``texture_probability``) or a plain colour.
    Kinds: diffuse 35 %, plastic 40 % (GGX alpha 0.03-0.5), rough conductor 25 % (alpha
    0.08-0.6, metal colours).
    """
    u = rng.random()
    kind = "diffuse" if u < 0.35 else ("plastic" if u < 0.75 else "conductor")
    roughness = float(rng.uniform(0.03, 0.5) if kind == "plastic" else rng.uniform(0.08, 0.6))
    ior = float(rng.uniform(1.4, 1.6))
    if has_own_appearance and rng.random() < own_probability:
        return Appearance(Material(kind, None, roughness, ior), label=f"{kind}/own")
    if rng.random() < texture_probability:
        tex_kind, tex = random_texture(rng, texture_size)
        tile = float(diameter * rng.uniform(0.3, 1.5))
        return Appearance(Material(kind, None, roughness, ior), tex, tile, f"{kind}/{tex_kind}")
    color = srgb_to_linear(random_color(rng, metal=kind == "conductor"))
    return Appearance(
        Material(kind, tuple(float(c) for c in color), roughness, ior), label=f"{kind}/color"
    )


def crease_normals(mesh: Mesh, angle_deg: float = 35.0) -> tuple[np.ndarray, np.ndarray]:
    """Unwelded corners of ``mesh``: (positions [F*3, 3], normals [F*3, 3]) with crease shading.

    Each face corner averages the (area-weighted) normals of the faces around its vertex whose
    normal is within ``angle_deg`` of its own face's: smooth over curved surfaces, sharp at CAD
    edges. Welded smooth normals would bend the shading of a box's faces toward its corners.
    """
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # |fn| = 2 area
    unit = fn / np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30)
    corner_face = np.repeat(np.arange(len(f)), 3)
    corner_vert = f.reshape(-1)
    # Pairs (corner c, face g) with g incident to the vertex of c.
    order = np.argsort(corner_vert, kind="stable")
    sv = corner_vert[order]
    starts = np.searchsorted(sv, np.arange(len(v)))
    counts = np.bincount(corner_vert, minlength=len(v))
    rep = counts[corner_vert]
    pair_corner = np.repeat(np.arange(len(corner_vert)), rep)
    offs = np.arange(len(pair_corner)) - np.repeat(np.cumsum(rep) - rep, rep)
    pair_face = corner_face[order[starts[corner_vert[pair_corner]] + offs]]
    keep = (unit[corner_face[pair_corner]] * unit[pair_face]).sum(1) >= math.cos(
        math.radians(angle_deg)
    )
    n = np.zeros((len(corner_vert), 3))
    np.add.at(n, pair_corner[keep], fn[pair_face[keep]])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(norm > 0, n / np.maximum(norm, 1e-30), unit[corner_face])
    return v[corner_vert], n


def box_uv_mesh(
    mesh: Mesh,
    texture: np.ndarray | None,
    tile_mm: float,
    rng: np.random.Generator,
    *,
    keep_normals: bool = False,
    angle_deg: float = 35.0,
) -> Mesh:
    """An unwelded copy of ``mesh`` with crease normals and, with ``texture``, box-projected UVs.

    Box (tri-planar) projection: each face takes the texture from the axis plane its normal
    points along most, u, v = the two other coordinates / ``tile_mm`` plus a random offset and
    a random rotation of the pattern. ``keep_normals`` keeps the mesh's own vertex normals
    (e.g. from a BOP PLY) instead of recomputing crease normals.
    """
    f = np.asarray(mesh.faces, np.int64)
    if keep_normals:
        pos = np.asarray(mesh.vertices, np.float64)[f.reshape(-1)]
        nrm = np.asarray(mesh.normals, np.float64)[f.reshape(-1)]
    else:
        pos, nrm = crease_normals(mesh, angle_deg)
    faces = np.arange(len(pos)).reshape(-1, 3)
    colors = None if mesh.colors is None else np.asarray(mesh.colors)[f.reshape(-1)]
    if texture is None:
        return Mesh(pos, faces, nrm, colors=colors, name=mesh.name, diameter=mesh.diameter)
    v = np.asarray(mesh.vertices, np.float64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    axis = np.repeat(np.abs(fn).argmax(1), 3)
    # The two in-plane coordinates of each projection axis.
    a = np.array([1, 0, 0])[axis], np.array([2, 2, 1])[axis]
    idx = np.arange(len(pos))
    uv = np.stack([pos[idx, a[0]], pos[idx, a[1]]], 1) / max(tile_mm, 1e-6)
    ang = rng.uniform(0, 2 * np.pi)
    rot = np.array([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]])
    uv = uv @ rot.T + rng.uniform(0, 1, 2)
    return Mesh(
        pos,
        faces,
        nrm,
        uv=uv.astype(np.float32),
        texture=np.ascontiguousarray(texture),
        name=mesh.name,
        diameter=mesh.diameter,
    )


# --------------------------------------------------------------------------------------------
# Support surfaces and backdrops.


def textured_rect(
    origin: np.ndarray,
    e1: np.ndarray,
    e2: np.ndarray,
    texture: np.ndarray,
    tile_mm: float,
    name: str = "rect",
    max_side: float = 3500.0,
) -> list[Mesh]:
    """A rectangle ``origin + s e1 + t e2`` (s, t in [0, 1]) facing ``e1 x e2``, with a tiled
    texture, as meshes of at most ``max_side`` mm per side.

    UVs are distances along e1 and e2 in units of ``tile_mm`` (Mitsuba wraps textures with
    ``repeat``), continuous across the pieces, so the texture repeats seamlessly every
    ``tile_mm``. Large surfaces are split because a ``Mesh`` is an object (at most 5 m across);
    the pieces share one texture array.
    """
    o, e1, e2 = (np.asarray(x, np.float64) for x in (origin, e1, e2))
    l1, l2 = float(np.linalg.norm(e1)), float(np.linalg.norm(e2))
    n1, n2 = max(1, math.ceil(l1 / max_side)), max(1, math.ceil(l2 / max_side))
    normal = np.cross(e1, e2)
    normal = np.tile(normal / np.linalg.norm(normal), (4, 1))
    out = []
    for i in range(n1):
        for j in range(n2):
            st = np.array([[i, j], [i + 1, j], [i + 1, j + 1], [i, j + 1]]) / [n1, n2]
            corners = o + st[:, :1] * e1 + st[:, 1:] * e2
            uv = st * [l1, l2] / tile_mm
            out.append(Mesh(corners, [[0, 1, 2], [0, 2, 3]], normal, uv=uv.astype(np.float32),
                            texture=texture, name=name))
    return out


def ground_plane(z: float, half_size: float, texture: np.ndarray, tile_mm: float) -> list[Mesh]:
    """A square of side ``2 half_size`` in the world plane z (mm), facing +z, as tiles."""
    s = half_size
    return textured_rect([-s, -s, z], [2 * s, 0, 0], [0, 2 * s, 0], texture, tile_mm, "ground")


def backdrop_walls(
    center: np.ndarray, distance: float, height: float, z0: float, texture: np.ndarray,
    tile_mm: float,
) -> list[Mesh]:
    """Four vertical walls (a room without ceiling) ``distance`` mm from ``center``, facing in."""
    c = np.array([float(center[0]), float(center[1]), z0])
    d = distance
    up = np.array([0.0, 0.0, height])
    out = []
    # Each wall runs clockwise around the room seen from above, so e1 x up points inward
    # (Mitsuba's BSDFs are one-sided).
    for (x0, y0), (x1, y1) in [((d, -d), (-d, -d)), ((d, d), (d, -d)), ((-d, d), (d, d)),
                               ((-d, -d), (-d, d))]:
        a = c + [x0, y0, 0.0]
        out += textured_rect(a, np.array([x1 - x0, y1 - y0, 0.0]), up, texture, tile_mm,
                             "backdrop")
    return out


# --------------------------------------------------------------------------------------------
# Environment.

# Mitsuba's envmap has +y up; the world is z up: local y -> world z, local z -> world -y.
_ENV_Y_UP_TO_Z_UP = np.array(
    [[1.0, 0, 0, 0], [0, 0, -1.0, 0], [0, 1.0, 0, 0], [0, 0, 0, 1.0]]
)


def sky_environment(
    rng: np.random.Generator, hw: tuple[int, int] = (64, 128)
) -> tuple[np.ndarray, np.ndarray]:
    """A procedural HDR environment: (equirectangular radiance float32 [h, w, 3], T_world_env).

    Sky gradient from a horizon to a zenith colour, a darker ground hemisphere, a sun (a Gaussian
    lobe 2-5 degrees wide, 0-60x brighter than the sky) and 0-3 soft rectangular "windows" near
    the horizon (indoor lighting). ``T_world_env`` turns Mitsuba's y-up map to the z-up world
    with a random yaw. Mean radiance is about 1 before the caller's scale.
    """
    h, w = hw
    el = (0.5 - (np.arange(h) + 0.5) / h)[:, None] * np.pi  # +pi/2 at the top row
    az = ((np.arange(w) + 0.5) / w)[None, :] * 2 * np.pi
    el, az = np.broadcast_arrays(el, az)
    horizon = srgb_to_linear(random_color(rng)) * 0.4 + 0.6
    zenith = srgb_to_linear(random_color(rng)) * rng.uniform(0.3, 1.0)
    ground = srgb_to_linear(random_color(rng)) * rng.uniform(0.05, 0.3)
    s = np.clip(np.sin(el), 0, 1)[..., None] ** rng.uniform(0.3, 1.0)
    img = np.where(el[..., None] >= 0, horizon * (1 - s) + zenith * s, ground)
    # Unit direction of every pixel (local frame: y up).
    d = np.stack([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)], -1)
    sun_el = rng.uniform(0.15, 1.4)
    sun_az = rng.uniform(0, 2 * np.pi)
    sun = np.array([math.cos(sun_el) * math.cos(sun_az), math.sin(sun_el),
                    math.cos(sun_el) * math.sin(sun_az)])
    width = math.radians(rng.uniform(2.0, 5.0))
    ang = np.arccos(np.clip(d @ sun, -1, 1))
    sun_gain = rng.uniform(0, 60) if rng.random() < 0.7 else 0.0
    sun_color = np.array([1.0, 0.95, 0.85])
    img = img + sun_gain * np.exp(-0.5 * (ang / width) ** 2)[..., None] * sun_color
    for _ in range(int(rng.integers(0, 4))):
        c_az = rng.uniform(0, 2 * np.pi)
        c_el = rng.uniform(0.0, 0.7)
        half_az, half_el = rng.uniform(0.1, 0.5), rng.uniform(0.05, 0.3)
        daz = np.angle(np.exp(1j * (az - c_az)))
        inside = (np.abs(daz) < half_az) & (np.abs(el - c_el) < half_el)
        img = img + inside[..., None] * rng.uniform(2, 10) * srgb_to_linear(random_color(rng))
    img = img / max(float(img.mean()), 1e-6)
    yaw = rng.uniform(0, 2 * np.pi)
    Rz = np.eye(4)
    Rz[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    return img.astype(np.float32), Rz @ _ENV_Y_UP_TO_Z_UP


def auto_exposure(linear: np.ndarray, key: float) -> np.ndarray:
    """Scale linear RGB [H, W, 3] so its log-average luminance is ``key`` (Reinhard et al. 2002)."""
    lum = linear @ np.array([0.2126, 0.7152, 0.0722])
    log_avg = float(np.exp(np.mean(np.log(1e-4 + np.maximum(lum, 0.0)))))
    return linear * (key / max(log_avg, 1e-6))


def to_uint8_srgb(linear: np.ndarray) -> np.ndarray:
    """Linear RGB [H, W, 3] -> uint8 sRGB (clipped, rounded)."""
    return np.round(linear_to_srgb(linear) * 255.0).astype(np.uint8)
