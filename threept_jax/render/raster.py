"""A pure-JAX triangle rasterizer: visibility buffer with tile work lists and one scatter-min.

docs/design.md section 4. Runs under ``jit`` and ``vmap`` on CPU, GPU and TPU, with no host
callbacks. The algorithm:

1. **Triangle setup** ``[B, F]``. For the ray ``d = K^-1 (u, v, 1)`` through pixel ``(u, v)``
   the hit on a triangle's plane is ``X = t d`` with ``t = (n . X0) / (n . d)``, and its
   barycentrics are ``b1 = (t d - X0) . g1``, ``b2 = (t d - X0) . g2`` (``g1, g2`` the dual basis
   of the edges). Since ``d_z = 1``, ``t`` is the depth z, and ``b0, b1, b2`` are the
   perspective-correct barycentrics. Each of ``n . d``, ``g1 . d``, ``g2 . d`` is affine in
   ``(u, v)``, so a triangle in a view is 12 numbers. ``n``, ``g1``, ``g2`` come from vertex
   differences in float64 on the host (``RasterMesh.face_geom``) and are rotated per view,
   which keeps float32 depth accurate for small triangles far away.
2. **Clipping**: a pixel counts only where ``t > near``, which clips triangles that cross the
   near plane exactly (no triangle is dropped); a triangle's pixel box is the box of its part in
   front of the near plane (vertices plus the edge crossings of ``z = near``).
3. **Window work list**: each triangle's pixel box is cut into ``tile x tile`` windows; a
   prefix sum over window counts lays them out as one list (culled, back-facing and off-screen
   triangles contribute none). The first ``chunk`` windows are rasterized in one pass; any rest
   (large triangles in a close-up) in a ``while_loop`` over smaller chunks. No pixel is ever
   dropped, and memory is ``chunk x tile^2``, never ``B x H x W x faces``.
4. **Visibility**: every window pixel inside its triangle writes a packed int32 key
   ``(quantised depth << id_bits) | face`` into the z-buffer with one ``.at[].min`` scatter.
   Depth is quantised over the mesh's bounding-sphere depth range of that view (with 2048
   faces, 20 bits: 2e-6 of the diameter), so interpenetrating triangles resolve correctly up to
   that step; ties go to the lower face index.
5. **Attributes**: each pixel gathers its winning (view, face) setup row, evaluates ``t`` and
   the barycentrics exactly as the visibility test did, and interpolates normals, colours and
   UVs from per-face corner tables; object coordinates are ``C + t R^T d``.

**Pixel convention** (``threept_jax.geometry.camera``): pixel ``(i, j)`` (column, row) is
sampled at exactly ``(u, v) = (i, j)`` of ``K``; a pixel centre on a shared edge belongs to
both triangles (inclusive test with a tolerance scaled to each triangle's float error, so no
cracks) and the z-buffer picks one.

**Culling**: back faces are skipped only for closed, consistently wound meshes
(``RasterMesh.cull_backfaces``); ``normal`` is the mesh's own (not flipped toward the camera).
"""

from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
from jax import lax

from threept_jax.render.mesh import RasterMesh

INT_MAX = 2**31 - 1
ALL_OUTPUTS = ("depth", "mask", "xyz", "normal", "rgb", "edge", "face_id")
DEFAULT_OUTPUTS = ("depth", "mask", "xyz", "normal")


class Fragments(NamedTuple):
    """Rasterizer output: the winning face per pixel and the per-(view, face) setup.

    face: [B, H, W] int32 face index, -1 for background.
    tri: [15, B * F] float32 setup rows (see :func:`_setup`); pixel (u, v) of face f in view b
      has depth z = det / (P . p) and barycentrics b1 = z (Q . p) - c1, b2 = z (S . p) - c2 with
      p = (u, v, 1) and the row index b * F + f.
    """

    face: jax.Array
    tri: jax.Array


def default_tile(hw: tuple[int, int]) -> int:
    """Window side for a render size: prepared meshes span a few pixels per edge at crop scale."""
    return 4 if max(hw) <= 256 else 8


def _id_bits(num_faces: int) -> tuple[int, int]:
    """(bits for the face id, bits for quantised depth) of a packed int32 key."""
    ib = max(1, math.ceil(math.log2(max(num_faces, 2))))
    db = min(31 - ib, 23)  # quantised depth goes through float32 bits (exact below 2^23)
    if db < 8:
        raise ValueError(
            f"{num_faces} faces leave {db} bits of depth in a packed key; decimate the mesh "
            "below 2^23 faces (prepare_mesh(max_faces=...))"
        )
    return ib, db


def inv_intrinsics(K: jax.Array) -> jax.Array:
    """Closed-form inverse of upper-triangular K [..., 3, 3] (fx, skew, cx; fy, cy; 0 0 1).

    ``jnp.linalg.inv`` would also work but costs seconds of XLA compilation per call site.
    """
    fx, s, cx = K[..., 0, 0], K[..., 0, 1], K[..., 0, 2]
    fy, cy = K[..., 1, 1], K[..., 1, 2]
    z, o = jnp.zeros_like(fx), jnp.ones_like(fx)
    rows = [
        [1.0 / fx, -s / (fx * fy), (s * cy - cx * fy) / (fx * fy)],
        [z, 1.0 / fy, -cy / fy],
        [z, z, o],
    ]
    return jnp.stack([jnp.stack(r, -1) for r in rows], -2)


def _materialize(xs, anchor):
    """Return ``xs`` (a pytree of arrays) computed once into buffers, on CPU.

    XLA:CPU drops optimization barriers and re-inlines producers into every consumer fusion,
    so a value read by several outputs (a triangle's setup, a pixel's barycentrics) would be
    recomputed by each. A conditional is a fusion boundary: its predicate (``anchor`` is never
    NaN) is data-dependent, so it cannot be folded away. Elsewhere (GPU, TPU) recomputation is
    cheap and a conditional costs a host sync, so this is the identity there.
    """
    if jax.default_backend() != "cpu":
        return xs
    return lax.cond(
        ~jnp.isnan(anchor),
        lambda: xs,
        lambda: jax.tree.map(jnp.zeros_like, xs),
    )


def _setup(mesh: RasterMesh, R, t, K, Kinv, hw, near, tile):
    """Per (view, face) setup rows and pixel boxes, flattened view-major (index b * F + f).

    Returns (tri [15, B*F] float32, box [5, B*F] int32 (x0, y0, x1, y1, nx), tiles [B*F]).
    tri rows: P (3) with n.d = P.(u, v, 1); det = n.X0; Q (3), c1; S (3), c2; tol; zlo; zscale.
    Written on [B, F] component arrays (views on rows, faces on columns): elementwise code that
    XLA fuses, rather than small matrix products.
    """
    H, W = hw
    B = R.shape[0]
    F = mesh.face_geom.shape[0]
    g = [mesh.face_geom[None, :, k] for k in range(18)]  # [1, F] each
    corner = [g[0:3], g[3:6], g[6:9]]
    n, g1, g2 = g[9:12], g[12:15], g[15:18]
    col = lambda a: a[:, None]  # noqa: E731  ([B] -> [B, 1])
    C = -jnp.einsum("bji,bj->bi", R, t)  # camera centres in the object frame [B, 3]
    M = jnp.einsum("bji,bjk->bik", Kinv, R)  # Kinv^T R: object-frame vector -> pixel-affine row
    rel = [corner[0][i] - col(C[:, i]) for i in range(3)]  # v0 - C  [B, F]
    dot = lambda a, b: a[0] * b[0] + a[1] * b[1] + a[2] * b[2]  # noqa: E731
    det, c1, c2 = dot(n, rel), dot(g1, rel), dot(g2, rel)
    aff = lambda x: [col(M[:, i, 0]) * x[0] + col(M[:, i, 1]) * x[1] + col(M[:, i, 2]) * x[2]  # noqa: E731
                     for i in range(3)]
    P, Q, S = aff(n), aff(g1), aff(g2)
    # Float32 error of b = t (Q.p) - c grows with |c| (distance / triangle size).
    tol = 4e-7 * (1.0 + jnp.abs(c1) + jnp.abs(c2))
    zc = jnp.sum(R[:, 2] * mesh.center, -1) + t[:, 2]
    zlo = jnp.maximum(zc - mesh.radius, near)
    zhi = jnp.maximum(zc + mesh.radius, zlo + 1e-3)
    _, db = _id_bits(F)
    zscale = (2.0**db - 1.0) / (zhi - zlo)
    full = lambda a: jnp.broadcast_to(col(a), (B, F))  # noqa: E731
    rows = P + [det] + Q + [c1] + S + [c2, tol, full(zlo), full(zscale)]
    tri = jnp.stack(rows, 0).reshape(15, B * F)

    # Pixel boxes of the part of each triangle in front of the near plane: its corners in front
    # and the crossings of its edges with z = near.
    X = [[col(R[:, i, 0]) * c[0] + col(R[:, i, 1]) * c[1] + col(R[:, i, 2]) * c[2]
          + col(t[:, i]) for i in range(3)] for c in corner]  # 3 corners x 3 coords, [B, F]
    front = [x[2] > near for x in X]
    k00, k01, k02 = col(K[:, 0, 0]), col(K[:, 0, 1]), col(K[:, 0, 2])
    k11, k12 = col(K[:, 1, 1]), col(K[:, 1, 2])
    big = 1e7
    umin = vmin = jnp.full((B, F), big)
    umax = vmax = jnp.full((B, F), -big)

    def include(x, y, z, ok, bounds):
        umin, umax, vmin, vmax = bounds
        zp = jnp.where(ok, jnp.maximum(z, near), 1.0)
        u = (k00 * x + k01 * y) / zp + k02
        v = k11 * y / zp + k12
        return (jnp.minimum(umin, jnp.where(ok, u, big)), jnp.maximum(umax, jnp.where(ok, u, -big)),
                jnp.minimum(vmin, jnp.where(ok, v, big)), jnp.maximum(vmax, jnp.where(ok, v, -big)))

    bounds = (umin, umax, vmin, vmax)
    for c in range(3):
        a, b = X[c], X[(c + 1) % 3]
        bounds = include(a[0], a[1], a[2], front[c], bounds)
        cross = front[c] != front[(c + 1) % 3]
        s = jnp.where(cross, (near - a[2]) / jnp.where(cross, b[2] - a[2], 1.0), 0.0)
        bounds = include(a[0] + s * (b[0] - a[0]), a[1] + s * (b[1] - a[1]), near, cross, bounds)
    umin, umax, vmin, vmax = bounds
    eps = 1e-3  # pixel centres on the box boundary are kept (inclusive test)
    x0 = jnp.maximum(jnp.ceil(jnp.clip(umin - eps, -2.0, W + 1.0)), 0)
    x1 = jnp.minimum(jnp.floor(jnp.clip(umax + eps, -2.0, W + 1.0)), W - 1)
    y0 = jnp.maximum(jnp.ceil(jnp.clip(vmin - eps, -2.0, H + 1.0)), 0)
    y1 = jnp.minimum(jnp.floor(jnp.clip(vmax + eps, -2.0, H + 1.0)), H - 1)
    visible = mesh.face_mask[None] & (front[0] | front[1] | front[2]) & (x0 <= x1) & (y0 <= y1)
    visible &= ~(mesh.cull_backfaces & (det >= 0))  # back-facing: plane normal away from camera
    x0, x1, y0, y1 = (a.astype(jnp.int32) for a in (x0, x1, y0, y1))
    nx = (x1 - x0) // tile + 1
    tiles = jnp.where(visible, nx * ((y1 - y0) // tile + 1), 0)
    box = jnp.stack([x0, y0, x1, y1, nx], 0).reshape(5, B * F)
    return _materialize((tri, box, tiles.reshape(B * F)), K[0, 0, 0])


def _scatter_windows(zbuf, item_f, item_i, *, tile, Wp, ib, qmax, near):
    """Evaluate tile x tile windows and scatter-min their packed keys into zbuf [B * Hp * Wp].

    item_f [15, N]: setup rows with the window origin folded into the constant terms;
    tol = -inf marks an empty item. item_i [2, N]: (flat z-buffer index of the window origin,
    face id).
    """
    # Materialise the per-item values once; otherwise XLA re-derives them (gathers, integer
    # divisions) for every pixel of every window.
    item_f, item_i = lax.optimization_barrier((item_f, item_i))
    dy, dx = jnp.meshgrid(jnp.arange(tile), jnp.arange(tile), indexing="ij")
    dxf = dx.reshape(1, -1).astype(jnp.float32)
    dyf = dy.reshape(1, -1).astype(jnp.float32)
    a = [item_f[i][:, None] for i in range(15)]
    t_ = a[3] / (a[0] * dxf + a[1] * dyf + a[2])
    b1 = t_ * (a[4] * dxf + a[5] * dyf + a[6]) - a[7]
    b2 = t_ * (a[8] * dxf + a[9] * dyf + a[10]) - a[11]
    tol = a[12]
    inside = (b1 >= -tol) & (b2 >= -tol) & (1.0 - b1 - b2 >= -tol) & (t_ > near)
    # Quantised depth as an int via the float bits of q + 2^23 (exact for q < 2^23).
    q = jnp.minimum(jnp.maximum((t_ - a[13]) * a[14], 0.0), qmax) + 2.0**23
    qi = lax.bitcast_convert_type(q, jnp.int32) - 0x4B000000
    key = jnp.where(inside, (qi << ib) | item_i[1][:, None], INT_MAX)
    idx = item_i[0][:, None] + (dy * Wp + dx).reshape(1, -1)
    return zbuf.at[idx.reshape(-1)].min(key.reshape(-1), mode="promise_in_bounds")


def rasterize(
    mesh: RasterMesh,
    R: jax.Array,
    t: jax.Array,
    K: jax.Array,
    hw: tuple[int, int],
    *,
    tile: int,
    chunk: int | None = None,
    near: float = 1.0,
) -> Fragments:
    """Visibility of mesh faces for B views: R [B, 3, 3], t [B, 3] (T_cam_obj), K [B, 3, 3].

    Args:
      hw: (H, W) image size.
      tile: window side in pixels (static); any value is exact, it only changes speed.
      chunk: windows per pass (static, default 1.25 B Fp); memory is chunk x tile^2 keys.
      near: near-plane depth in mm; surfaces at z <= near are clipped.

    Windows of visible triangles are listed by a prefix sum over their counts (culled and
    off-screen triangles take none) and rasterized ``chunk`` at a time by one ``while_loop``,
    which runs once in the common case and again only for large triangles and close-ups. One
    loop body, so XLA compiles the pass once (a first pass outside the loop cost a second
    copy: a third of the renderer's compile time).
    """
    H, W = hw
    B = R.shape[0]
    F = mesh.face_geom.shape[0]
    ib, db = _id_bits(F)
    tri, box, tiles = _setup(mesh, R, t, K, inv_intrinsics(K), hw, near, tile)
    BF = B * F
    # A pass holds 1.25 windows per (view, face): every visible triangle of a prepared
    # mesh, culled or not, in the common case.
    C = int(chunk) if chunk is not None else BF + BF // 4
    Hp, Wp = H + tile, W + tile  # z-buffer padded so every window stays in bounds
    kw = dict(tile=tile, Wp=Wp, ib=ib, qmax=2.0**db - 1.0, near=near)
    tri_ids = jnp.arange(BF, dtype=jnp.int32)

    def items(r, bx, owner, k, live):
        """Per-item rows for window k of triangles ``owner`` [N] (setup r [15, N], bx [5, N])."""
        ty = k // bx[4]
        ox = bx[0] + (k - ty * bx[4]) * tile
        oy = bx[1] + ty * tile
        oxf, oyf = ox.astype(jnp.float32), oy.astype(jnp.float32)
        img = owner // F
        item_f = jnp.stack(
            [
                r[0], r[1], r[0] * oxf + r[1] * oyf + r[2], r[3],
                r[4], r[5], r[4] * oxf + r[5] * oyf + r[6], r[7],
                r[8], r[9], r[8] * oxf + r[9] * oyf + r[10], r[11],
                jnp.where(live, r[12], -jnp.inf), r[13], r[14],
            ],
            0,
        )
        item_i = jnp.stack([(img * Hp + oy) * Wp + ox, owner - img * F], 0)
        return item_f, item_i

    incl = jnp.cumsum(tiles)
    start = incl - tiles
    total = incl[-1]

    def run(zbuf, base, n):
        """Scatter work items [base, base + n) of the prefix-summed window list."""
        # Owner triangle of each item: scatter each triangle's first item, fill forward.
        in_chunk = (tiles > 0) & (start >= base) & (start < base + n)
        pos = jnp.where(in_chunk, start - base, n)
        owner = jnp.zeros((n,), jnp.int32).at[pos].max(tri_ids, mode="drop")
        first = jnp.searchsorted(incl, base, side="right").astype(jnp.int32)
        owner = jnp.minimum(lax.cummax(owner.at[0].max(first)), BF - 1)
        w = base + jnp.arange(n, dtype=jnp.int32)
        it = items(tri[:, owner], box[:, owner], owner, w - start[owner], w < total)
        return _scatter_windows(zbuf, *it, **kw)

    _, zbuf = lax.while_loop(
        lambda s: s[0] * C < total,
        lambda s: (s[0] + 1, run(s[1], s[0] * C, C)),
        (jnp.int32(0), jnp.full((B * Hp * Wp,), INT_MAX, jnp.int32)),
    )
    zbuf = zbuf.reshape(B, Hp, Wp)[:, :H, :W]
    return Fragments(face=jnp.where(zbuf == INT_MAX, -1, zbuf & ((1 << ib) - 1)), tri=tri)


def edges_from_geometry(mask, points, normal, depth_threshold, angle_deg=45.0, xp=jnp):
    """Edge pixels [..., H, W] bool from mask, camera-frame points and face normals [..., H, W, 3].

    A foreground pixel p is an edge if a 4-neighbour q inside the image is background
    (silhouette); or lies farther and more than ``depth_threshold`` mm off p's face plane,
    ``|n_p . (P_q - P_p)|`` (p occludes q: a depth discontinuity; slanted planes give none);
    or has a face normal more than ``angle_deg`` away (a crease). ``xp`` is numpy or
    jax.numpy, so both backends share this definition.
    """
    cos_t = xp.cos(xp.deg2rad(angle_deg))
    edge = xp.zeros(mask.shape, bool)
    for axis in (-2, -1):
        for shift in (1, -1):
            sl_a = [slice(None)] * mask.ndim
            sl_b = [slice(None)] * mask.ndim
            sl_a[axis] = slice(1, None) if shift == 1 else slice(None, -1)
            sl_b[axis] = slice(None, -1) if shift == 1 else slice(1, None)
            a, b = tuple(sl_a), tuple(sl_b)  # pixel a, its neighbour b
            na, nb = normal[a + (slice(None),)], normal[b + (slice(None),)]
            pa, pb = points[a + (slice(None),)], points[b + (slice(None),)]
            off_plane = xp.abs((na * (pb - pa)).sum(-1)) > depth_threshold
            behind = pb[..., 2] > pa[..., 2]
            e = mask[a] & (~mask[b] | (behind & off_plane) | ((na * nb).sum(-1) < cos_t))
            pad = [(0, 0)] * mask.ndim
            pad[axis] = (1, 0) if shift == 1 else (0, 1)
            edge = edge | xp.pad(e, pad)
    return edge


def shade(albedo, normal, view_dir, ambient):
    """Headlight Lambert shading: albedo * (ambient + (1 - ambient) |n . v|), in [0, 1].

    Two-sided, so inward-wound meshes are lit too. albedo, normal, view_dir [..., 3].
    """
    lam = jnp.abs(jnp.sum(normal * view_dir, -1, keepdims=True))
    return jnp.clip(albedo * (ambient + (1.0 - ambient) * lam), 0.0, 1.0)


def _sample_texture(texture, uv):
    """Bilinear lookup of texture [Ht, Wt, 3] uint8 at uv [..., 2] (OpenGL v, repeat wrap)."""
    Ht, Wt = texture.shape[:2]
    x = uv[..., 0] * Wt - 0.5
    y = (1.0 - uv[..., 1]) * Ht - 0.5
    x0f, y0f = jnp.floor(x), jnp.floor(y)
    fx, fy = (x - x0f)[..., None], (y - y0f)[..., None]
    x0 = jnp.mod(x0f.astype(jnp.int32), Wt)
    y0 = jnp.mod(y0f.astype(jnp.int32), Ht)
    x1, y1 = jnp.mod(x0 + 1, Wt), jnp.mod(y0 + 1, Ht)
    tex = texture.astype(jnp.float32) / 255.0
    top = tex[y0, x0] * (1 - fx) + tex[y0, x1] * fx
    bot = tex[y1, x0] * (1 - fx) + tex[y1, x1] * fx
    return top * (1 - fy) + bot * fy


def _interpolate(mesh, frags, R, t, K, need, ambient, edge_depth_fraction, edge_angle_deg):
    """Per-pixel outputs from the winning faces.

    Each pixel gathers its (view, face) setup row, the same numbers that decided visibility, and
    evaluates depth and perspective-correct barycentrics with a few multiply-adds; object
    coordinates are the camera centre plus depth times the pixel's object-frame ray; per-corner
    attributes come from a second, per-face table. Written per component on [B, H, W] arrays so
    that XLA emits few, large elementwise fusions.
    """
    face = frags.face
    B, H, W = face.shape
    F = mesh.face_geom.shape[0]
    mask = face >= 0
    fsafe = jnp.maximum(face, 0)
    rows = frags.tri[:12].T[jnp.arange(B, dtype=jnp.int32)[:, None, None] * F + fsafe]
    r = [rows[..., i] for i in range(12)]
    u = jnp.arange(W, dtype=jnp.float32)[None, None, :]
    v = jnp.arange(H, dtype=jnp.float32)[None, :, None]
    z = jnp.where(mask, r[3] / (r[0] * u + r[1] * v + r[2]), 0.0)
    b1 = z * (r[4] * u + r[5] * v + r[6]) - r[7]
    b2 = z * (r[8] * u + r[9] * v + r[10]) - r[11]
    z, b1, b2 = _materialize((z, b1, b2), K[0, 0, 0])
    b0 = 1.0 - b1 - b2
    A = jnp.einsum("bji,bjk->bik", R, inv_intrinsics(K))[:, :, :, None, None]  # ray: A (u,v,1)
    C = -jnp.einsum("bji,bj->bi", R, t)[:, :, None, None]
    Rb = R[:, :, :, None, None]
    Kb = K[:, :, :, None, None]
    d = [A[:, i, 0] * u + A[:, i, 1] * v + A[:, i, 2] for i in range(3)]  # object frame, z_cam 1
    out = {}
    if "depth" in need:
        out["depth"] = z
    if "xyz" in need:
        out["xyz"] = jnp.stack([jnp.where(mask, C[:, i] + z * d[i], 0.0) for i in range(3)], -1)

    def unit(y):
        inv = lax.rsqrt(jnp.maximum(y[0] * y[0] + y[1] * y[1] + y[2] * y[2], 1e-30))
        return [jnp.where(mask, yi * inv, 0.0) for yi in y]

    if need & {"normal", "rgb"}:
        cn = mesh.corner_normals[fsafe]  # [B, H, W, 9], one contiguous row per pixel
        n_obj = [b0 * cn[..., i] + b1 * cn[..., 3 + i] + b2 * cn[..., 6 + i] for i in range(3)]
        n_cam = unit([Rb[:, i, 0] * n_obj[0] + Rb[:, i, 1] * n_obj[1] + Rb[:, i, 2] * n_obj[2]
                      for i in range(3)])
        if "normal" in need:
            out["normal"] = jnp.stack(n_cam, -1)
    if "rgb" in need:
        cc = mesh.corner_colors[fsafe]
        albedo = jnp.stack([b0 * cc[..., i] + b1 * cc[..., 3 + i] + b2 * cc[..., 6 + i]
                            for i in range(3)], -1)
        if mesh.has_texture:
            cu = mesh.corner_uv[fsafe]
            uv = [b0 * cu[..., i] + b1 * cu[..., 2 + i] + b2 * cu[..., 4 + i] for i in range(2)]
            albedo = albedo * _sample_texture(mesh.texture, jnp.stack(uv, -1))
        # Toward the camera: -R d (camera frame).
        view = unit([-(Rb[:, i, 0] * d[0] + Rb[:, i, 1] * d[1] + Rb[:, i, 2] * d[2])
                     for i in range(3)])
        rgb = shade(albedo, jnp.stack(n_cam, -1), jnp.stack(view, -1), ambient)
        out["rgb"] = jnp.where(mask[..., None], rgb, 0.0)
    if "edge" in need:
        # Face normal in the camera frame from the setup row: P = K^-T n_cam, so n_cam = K^T P.
        ng = jnp.stack(unit([Kb[:, 0, i] * r[0] + Kb[:, 1, i] * r[1] + Kb[:, 2, i] * r[2]
                             for i in range(3)]), -1)
        Kinv = inv_intrinsics(K)[:, :, :, None, None]
        pts = jnp.stack([z * (Kinv[:, i, 0] * u + Kinv[:, i, 1] * v + Kinv[:, i, 2])
                         for i in range(3)], -1)  # camera frame: z K^-1 (u, v, 1)
        out["edge"] = edges_from_geometry(
            mask, pts, ng, edge_depth_fraction * mesh.diameter, edge_angle_deg
        )
    return out


def _render_impl(
    mesh: RasterMesh,
    T_cam_obj,
    K,
    near,
    ambient,
    edge_depth_fraction,
    edge_angle_deg,
    *,
    hw,
    outputs,
    tile,
    chunk,
):
    """Render B views: T_cam_obj [B, 4, 4], K [B, 3, 3] (flattened by :func:`render`)."""
    R, t = T_cam_obj[:, :3, :3], T_cam_obj[:, :3, 3]
    frags = rasterize(mesh, R, t, K, hw, tile=tile, chunk=chunk, near=near)
    face = frags.face
    mask = face >= 0
    out = {}
    if "face_id" in outputs:
        out["face_id"] = face
    if "mask" in outputs:
        out["mask"] = mask
    need = set(outputs) - {"mask", "face_id"}
    if need:
        out.update(_interpolate(mesh, frags, R, t, K, need, ambient, edge_depth_fraction,
                                edge_angle_deg))
    return out


#: XLA options of the rasterizer's program: on CPU, XLA's classic loop emitters instead of its
#: MLIR fusion emitters (a CPU-only option; other backends ignore it). Measured on 2 cores, T-LESS
#: obj 4 at 2048 faces, depth/mask/xyz/normal: 128 x 128 x 64 views compile 1.58 -> 0.87 s, run
#: 89 -> 86 ms; 640 x 480 x 4 views 1.59 -> 0.83 s, run 64 -> 52 ms (docs/rendering.md).
#: JAX takes compiler options on a top-level jit only: inside another transformation's trace
#: (:func:`render` called under ``jit``, ``vmap``, ``grad``) the program is part of the caller's.
RASTER_COMPILE_OPTIONS = {"xla_cpu_use_fusion_emitters": False}
_STATIC = ("hw", "outputs", "tile", "chunk")
_render_jit = jax.jit(_render_impl, static_argnames=_STATIC, compiler_options=RASTER_COMPILE_OPTIONS)
_render_traced = jax.jit(_render_impl, static_argnames=_STATIC)


def render(
    mesh: RasterMesh,
    T_cam_obj: jax.Array,
    K: jax.Array,
    hw: tuple[int, int],
    outputs: Sequence[str] = DEFAULT_OUTPUTS,
    *,
    tile: int | None = None,
    chunk: int | None = None,
    near: float = 1.0,
    ambient: float = 0.3,
    edge_depth_fraction: float = 0.02,
    edge_angle_deg: float = 45.0,
) -> dict[str, jax.Array]:
    """Render a :class:`RasterMesh` at poses T_cam_obj [..., 4, 4] with K [..., 3, 3].

    Jit-compiled (one compilation per mesh bucket, image size, outputs, tile and batch shape);
    callable inside ``jit``/``vmap``. Returns arrays [..., H, W, ...] keyed by ``outputs``:
    ``depth`` (z in mm, 0 = background), ``mask`` (bool), ``xyz`` (object coordinates in mm),
    ``normal`` (unit, camera frame, the mesh's interpolated vertex normal), ``rgb`` (albedo from
    texture, vertex colour or grey, with :func:`shade` headlight lighting), ``edge`` (bool,
    :func:`edges_from_geometry`, off-plane threshold ``edge_depth_fraction`` x diameter),
    ``face_id`` (int32, -1 = background). Background pixels are 0 / False.

    ``tile`` defaults to :func:`default_tile`; ``chunk`` bounds memory (see :func:`rasterize`).
    """
    outputs = tuple(dict.fromkeys(outputs))
    bad = [o for o in outputs if o not in ALL_OUTPUTS]
    if bad:
        raise ValueError(f"unknown outputs {bad}; choose from {ALL_OUTPUTS}")
    hw = (int(hw[0]), int(hw[1]))
    tile = default_tile(hw) if tile is None else int(tile)
    if tile < 1:
        raise ValueError(f"tile must be >= 1, got {tile}")
    T_cam_obj = jnp.asarray(T_cam_obj, jnp.float32)
    lead = T_cam_obj.shape[:-2]
    # Flat views and one K per view, so that any leading shape and a shared K or per-view Ks
    # all hit the same compiled function.
    K = jnp.broadcast_to(jnp.asarray(K, jnp.float32), lead + (3, 3)).reshape(-1, 3, 3)
    args = (mesh, T_cam_obj.reshape(-1, 4, 4), K, jnp.float32(near), jnp.float32(ambient),
            jnp.float32(edge_depth_fraction), jnp.float32(edge_angle_deg))
    # Under a staging trace (jit, eval_shape) even constants are tracers here.
    traced = any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(args))
    out = (_render_traced if traced else _render_jit)(*args, hw=hw, outputs=outputs, tile=tile,
                                                      chunk=chunk)
    return {k: v.reshape(lead + v.shape[1:]) for k, v in out.items()}
