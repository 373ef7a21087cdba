"""Both backends against OpenCV projections of mesh vertices, and against each other.

Shared BOP meshes, decimated to <= 1500 faces (padded to one face bucket, so the JAX renderer
compiles once per image size), anisotropic K with off-centre principal points.
"""

import cv2
import numpy as np
import pytest

from threept_jax.render import Renderer, render

B = 8
BUCKET = 1536
OUTPUTS = ("depth", "mask", "xyz", "normal", "rgb", "edge", "face_id")
MESHES = [("tless", 4), ("itodd", 15), ("tudl", 3), ("ycbv", 10)]


def _K(hw, seed):
    H, W = hw
    rng = np.random.default_rng(seed)
    fy = 1.6 * H
    return np.array([[fy * 1.15, 0, W / 2 - 0.5 + 6 * rng.standard_normal()],
                     [0, fy, H / 2 - 0.5 + 4 * rng.standard_normal()], [0, 0, 1]])


@pytest.fixture(scope="module")
def renderers(bop_mesh):
    cache = {}

    def get(dataset, obj_id, backend):
        key = (dataset, obj_id, backend)
        if key not in cache:
            mesh = bop_mesh(dataset, obj_id)
            if backend == "jax":
                from threept_jax.render import to_raster_mesh

                cache[key] = Renderer(to_raster_mesh(mesh, face_bucket=BUCKET))
            else:
                cache[key] = Renderer(mesh, "mitsuba")
        return cache[key]

    return get


def _np(out):
    return {k: np.asarray(v) for k, v in out.items()}


@pytest.mark.parametrize("hw", [(128, 128), (192, 256)])
@pytest.mark.parametrize("dataset,obj_id", MESHES)
def test_backends_agree(dataset, obj_id, hw, renderers, bop_mesh, poses):
    mesh = bop_mesh(dataset, obj_id)
    T = poses(mesh, B, seed=obj_id, distance_factor=2.2)
    K = _K(hw, obj_id)
    a = _np(renderers(dataset, obj_id, "jax").render(T, K, hw, OUTPUTS))
    b = _np(renderers(dataset, obj_id, "mitsuba").render(T, K, hw, OUTPUTS))
    ma, mb = a["mask"], b["mask"]
    assert ma.sum() > 0.05 * ma.size
    assert (ma & mb).sum() / (ma | mb).sum() >= 0.98
    both = ma & mb
    assert np.median(np.abs(a["depth"] - b["depth"])[both]) < 0.2
    assert np.median(np.linalg.norm(a["xyz"] - b["xyz"], axis=-1)[both]) < 0.5
    cos = (a["normal"] * b["normal"]).sum(-1)[both]
    assert np.median(cos) > np.cos(np.radians(1.0))
    assert (a["face_id"] == b["face_id"])[both].mean() > 0.97
    assert np.median(np.abs(a["rgb"] - b["rgb"])[both]) < 0.01
    ea, eb = a["edge"], b["edge"]
    assert (ea & eb).sum() / (ea | eb).sum() > 0.85
    # Background is 0 / False / -1 in both.
    for out in (a, b):
        assert not out["depth"][~out["mask"]].any() and not out["edge"][~out["mask"]].any()
        assert np.all(out["face_id"][~out["mask"]] == -1)


def _visible_vertices(mesh, T, n_max=64):
    """Vertices not occluded from the camera of T (float64 segment tests, independent of both
    renderers), with every incident face turned toward the camera (so not on a silhouette)."""
    V = mesh.vertices.astype(np.float64)
    F = mesh.faces
    C = -T[:3, :3].T @ T[:3, 3]
    tri = V[F]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    front = np.einsum("fi,fi->f", n, tri[:, 0] - C) < 0
    all_front = np.ones(len(V), bool)
    np.logical_and.at(all_front, F.ravel(), np.repeat(front, 3))
    used = np.zeros(len(V), bool)
    used[F.ravel()] = True
    cand = np.nonzero(all_front & used)[0]
    rng = np.random.default_rng(0)
    cand = rng.permutation(cand)[: 6 * n_max]
    d = V[cand] - C  # segments C -> V
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    pvec = np.cross(d[:, None], e2[None])
    det = np.einsum("fi,vfi->vf", e1, pvec)
    inv = 1.0 / np.where(np.abs(det) > 1e-12, det, np.inf)
    s = C - tri[:, 0]
    a = np.einsum("fi,vfi->vf", s, pvec) * inv
    q = np.cross(s, e1)
    b = np.einsum("vi,fi->vf", d, q) * inv
    t = np.einsum("fi,fi->f", e2, q)[None] * inv
    incident = (F[None, :, :] == cand[:, None, None]).any(-1)
    blocked = (a >= 0) & (b >= 0) & (a + b <= 1) & (t > 1e-6) & (t < 1 - 1e-6) & ~incident
    return cand[~blocked.any(1)][:n_max]


def _probes(mesh, vertices, eps=0.05):
    """Points just inside a face incident to each vertex: P = V + eps (centroid - V).

    Ray casters may leak through a ray that passes exactly through a vertex (Embree does), so
    the probes sit strictly inside a triangle, 5 % of the way to its centroid. Returns points
    [n, 3], the face [n] and barycentric weights [n, 3] of the face's corners.
    """
    F = mesh.faces
    face = np.array([np.nonzero((F == v).any(1))[0][0] for v in vertices])
    corner = np.argmax(F[face] == vertices[:, None], axis=1)
    w = np.full((len(vertices), 3), eps / 3)
    w[np.arange(len(vertices)), corner] += 1 - eps
    P = np.einsum("nk,nki->ni", w, mesh.vertices.astype(np.float64)[F[face]])
    return P, face, w


@pytest.mark.parametrize("backend", ["jax", "mitsuba"])
@pytest.mark.parametrize("dataset,obj_id", [("tless", 4), ("tudl", 3)])
def test_vertices_against_opencv_projection(dataset, obj_id, backend, renderers, bop_mesh, poses):
    """cv2.projectPoints of visible vertices: each lands in the mask; and a view whose
    principal point is shifted so that a surface point next to the vertex falls on a pixel
    centre renders that point's z (within 0.5 mm), object coordinates and (unlit) its
    interpolated vertex colour there."""
    mesh = bop_mesh(dataset, obj_id)
    hw = (128, 128)
    r = renderers(dataset, obj_id, backend)
    T = poses(mesh, B, seed=7, distance_factor=2.2)
    K = _K(hw, 1)
    full = _np(r.render(T, K, hw, OUTPUTS))
    checked = 0
    for b in range(2):
        vis = _visible_vertices(mesh, T[b])
        rvec = cv2.Rodrigues(T[b, :3, :3])[0]
        pts = mesh.vertices[vis].astype(np.float64)
        uv = cv2.projectPoints(pts, rvec, T[b, :3, 3], K, None)[0][:, 0]
        inside = (uv[:, 0] > 1) & (uv[:, 0] < hw[1] - 2) & (uv[:, 1] > 1) & (uv[:, 1] < hw[0] - 2)
        vis, uv = vis[inside], uv[inside]
        assert len(vis) >= B
        # Every visible vertex lands in the mask (within the one-pixel rounding of its centre).
        m = full["mask"][b]
        dil = m | np.roll(m, 1, 0) | np.roll(m, -1, 0) | np.roll(m, 1, 1) | np.roll(m, -1, 1)
        ij = np.round(uv).astype(int)
        assert dil[ij[:, 1], ij[:, 0]].all()
        # Aligned views: shift the principal point so that probe k (a point of the surface
        # next to vertex k) projects onto a pixel centre; that pixel must render its z.
        sel = vis[:B]
        P, face, w = _probes(mesh, sel)
        uvs = cv2.projectPoints(P, rvec, T[b, :3, 3], K, None)[0][:, 0]
        Ks = np.tile(K, (B, 1, 1))
        Ks[:, :2, 2] += np.round(uvs) - uvs
        out = _np(r.render(np.repeat(T[b : b + 1], B, 0), Ks, hw, OUTPUTS, ambient=1.0))
        pix = np.round(uvs).astype(int)
        k = np.arange(B)
        z = (P @ T[b, :3, :3].T + T[b, :3, 3])[:, 2]
        assert out["mask"][k, pix[:, 1], pix[:, 0]].all()
        np.testing.assert_allclose(out["depth"][k, pix[:, 1], pix[:, 0]], z, atol=0.5)
        np.testing.assert_allclose(out["xyz"][k, pix[:, 1], pix[:, 0]], P, atol=0.5)
        if mesh.colors is not None:  # TUD-L: vertex-coloured
            ref = np.einsum("nk,nkc->nc", w, mesh.colors[mesh.faces[face]])
            np.testing.assert_allclose(out["rgb"][k, pix[:, 1], pix[:, 0]], ref, atol=2e-3)
        checked += B
    assert checked == 2 * B


@pytest.mark.parametrize("backend", ["jax", "mitsuba"])
def test_texture_is_rendered(backend, renderers, bop_mesh, poses):
    """YCB-V obj 10 (UV-textured): the unlit colour at a surface point's pixel centre equals the
    texture sampled bilinearly (cv2.remap) at the point's UV (OpenGL v, texel centres at
    (i + 0.5) / size), interpolated from its face's corners."""
    mesh = bop_mesh("ycbv", 10)
    assert mesh.texture is not None and mesh.texture.shape == (1024, 1024, 3)
    r = renderers("ycbv", 10, backend)
    hw = (128, 128)
    T = poses(mesh, 1, seed=2, distance_factor=2.0)[0]
    K = _K(hw, 3)
    vis = _visible_vertices(mesh, T, n_max=64)
    rvec = cv2.Rodrigues(T[:3, :3])[0]
    P, face, w = _probes(mesh, vis)
    uv = cv2.projectPoints(P, rvec, T[:3, 3], K, None)[0][:, 0]
    ok = (uv[:, 0] > 1) & (uv[:, 0] < 126) & (uv[:, 1] > 1) & (uv[:, 1] < 126)
    uvs, face, w = uv[ok][:B], face[ok][:B], w[ok][:B]
    assert len(uvs) == B
    Ks = np.tile(K, (B, 1, 1))
    Ks[:, :2, 2] += np.round(uvs) - uvs
    out = _np(r.render(np.repeat(T[None], B, 0), Ks, hw, OUTPUTS, ambient=1.0))
    pix = np.round(uvs).astype(int)
    got = out["rgb"][np.arange(B), pix[:, 1], pix[:, 0]]
    tex = mesh.texture.astype(np.float32) / 255.0
    h, w_ = tex.shape[:2]
    tu = np.einsum("nk,nkc->nc", w, mesh.uv[mesh.faces[face]])
    mapx = (tu[:, 0] * w_ - 0.5).astype(np.float32)[None]
    mapy = ((1 - tu[:, 1]) * h - 0.5).astype(np.float32)[None]
    ref = cv2.remap(tex, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)[0]
    np.testing.assert_allclose(got, ref, atol=0.02)
    # The texture really varies over these vertices (not a flat colour that would pass anyway).
    assert ref.std(0).max() > 0.05


@pytest.mark.parametrize("backend", ["jax", "mitsuba"])
def test_bad_poses(backend, renderers):
    r = renderers("tless", 4, backend)
    hw = (128, 128)
    K = _K(hw, 0)
    T = np.tile(np.eye(4), (B, 1, 1))
    T[:, 2, 3] = -np.linspace(50, 800, B)  # behind the camera
    out = _np(r.render(T, K, hw, OUTPUTS))
    assert not out["mask"].any() and not out["depth"].any()
    with pytest.raises(ValueError, match="not a rigid transform"):
        T2 = T.copy()
        T2[:, :3, :3] *= 0.0
        r.render(T2, K, hw)
    with pytest.raises(ValueError, match="fx > 0"):
        K2 = K.copy()
        K2[0, 0] = -K2[0, 0]
        render(r, np.tile(np.eye(4), (B, 1, 1)), K2, hw)
