"""The JAX rasterizer against hand-derived scenes and a brute-force float64 ray caster.

All synthetic meshes are padded to one face bucket and rendered at one size and batch, so the
module compiles the renderer once (plus one close-up configuration and one vmap trace).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from threept_jax.render import Mesh, check_pose_and_intrinsics, raster, render, to_raster_mesh

# One compiled configuration for every synthetic mesh: 512 padded faces, 48x64, 4 views.
SYNTH_BUCKET, SYNTH_HW, SYNTH_B = 512, (48, 64), 4
ALL = ("depth", "mask", "xyz", "normal", "rgb", "edge", "face_id")
H, W = SYNTH_HW


def _rm(mesh, **kw):
    return to_raster_mesh(mesh, face_bucket=SYNTH_BUCKET, **kw)


def _render(rmesh, T, K, **kw):
    out = raster.render(rmesh, jnp.asarray(T, jnp.float32), jnp.asarray(K, jnp.float32),
                        SYNTH_HW, ALL, **kw)
    return {k: np.asarray(v) for k, v in out.items()}


def _quad(x0, x1, y0, y1, z=lambda x, y: 100.0 + 0 * x, colors=None):
    """Two triangles over [x0, x1] x [y0, y1] at depth z(x, y), facing -z (toward the camera)."""
    xy = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], np.float64)
    v = np.concatenate([xy, z(xy[:, 0], xy[:, 1])[:, None]], 1)
    f = np.array([[0, 2, 1], [0, 3, 2]])  # counter-clockwise seen from -z
    c = None if colors is None else colors(v)
    return Mesh(vertices=v, faces=f, colors=c, name="quad")


def _K(fx, fy, cx, cy):
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float64)


def _eye(B=SYNTH_B):
    return np.tile(np.eye(4), (B, 1, 1))


def test_pixel_centre_convention():
    """Pixel (i, j) is sampled at (u, v) = (i, j) of K: an axis-aligned quad covers exactly the
    columns i with u0 <= i <= u1, for principal points on and between pixel centres."""
    quad = _quad(-21.9, -11.1, -17.3, -9.9)
    Ks = np.stack([_K(100, 100, 31.5, 23.5), _K(100, 100, 32.0, 23.0), _K(120, 90, 30.25, 22.6),
                   _K(80, 110, 33.7, 24.05)])
    out = _render(_rm(quad), _eye(), Ks)
    for b, K in enumerate(Ks):
        u0, u1 = K[0, 0] * -21.9 / 100 + K[0, 2], K[0, 0] * -11.1 / 100 + K[0, 2]
        v0, v1 = K[1, 1] * -17.3 / 100 + K[1, 2], K[1, 1] * -9.9 / 100 + K[1, 2]
        i, j = np.arange(W), np.arange(H)
        expect = ((j >= v0) & (j <= v1))[:, None] & ((i >= u0) & (i <= u1))[None, :]
        np.testing.assert_array_equal(out["mask"][b], expect)
        np.testing.assert_allclose(out["depth"][b][expect], 100.0, rtol=1e-6)
        assert np.all(out["depth"][b][~expect] == 0)
        # Object coordinates of pixel (i, j): X = (i - cx) z / fx.
        jj, ii = np.nonzero(expect)
        xyz = np.stack([(ii - K[0, 2]) / K[0, 0] * 100, (jj - K[1, 2]) / K[1, 1] * 100,
                        np.full(len(ii), 100.0)], -1)
        np.testing.assert_allclose(out["xyz"][b][expect], xyz, atol=1e-3)


def _plane_hits(T, K, n_obj, c_obj):
    """Object-frame hit points [H, W, 3] and depth of every pixel ray with plane n.X = c."""
    R, t = T[:3, :3], T[:3, 3]
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    d_cam = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
    d_obj = d_cam @ R  # R^T d
    C = -R.T @ t
    z = (c_obj - n_obj @ C) / (d_obj @ n_obj)
    return C + z[..., None] * d_obj, z


def test_perspective_correct_interpolation():
    """Vertex colours linear in position interpolate to exactly that linear function at each
    pixel's hit point (screen-space affine interpolation would not); depth is the analytic
    ray-plane distance. Slanted plane z = 100 + 0.4 x, rotated pose, fx != fy."""
    M = np.array([[3e-3, 1e-3, 2e-3], [1e-3, 3e-3, -2e-3], [0.0, 0.0, 0.0]])
    lin = lambda v: np.clip(0.5 + v @ M, 0, 1)  # noqa: E731
    quad = _quad(-60, 60, -45, 45, z=lambda x, y: 100 + 0.4 * x, colors=lin)
    from scipy.spatial.transform import Rotation

    T = _eye()
    for b in range(SYNTH_B):
        T[b, :3, :3] = Rotation.from_euler("xyz", [0.1 * b, -0.2 + 0.1 * b, 0.05]).as_matrix()
        T[b, :3, 3] = [3.0 * b, -2.0, 120.0 - 40 * T[b, 2, :3] @ [0, 0, 1]]
    K = _K(70, 55, 30.2, 24.9)
    out = _render(_rm(quad), T, K, ambient=1.0)
    n_obj, c_obj = np.array([-0.4, 0.0, 1.0]), 100.0
    for b in range(SYNTH_B):
        p, z = _plane_hits(T[b], K, n_obj, c_obj)
        inside = (np.abs(p[..., 0]) < 59) & (np.abs(p[..., 1]) < 44) & (z > 0)
        assert inside.sum() > 500
        m = out["mask"][b]
        assert np.all(m[inside])
        np.testing.assert_allclose(out["depth"][b][inside], z[inside], rtol=2e-5)
        np.testing.assert_allclose(out["xyz"][b][inside], p[inside], atol=2e-3)
        np.testing.assert_allclose(out["rgb"][b][inside], lin(p[inside]), atol=2e-5)


def test_interpenetrating_triangles():
    """Two quads crossing along x = 0: each pixel shows the nearer plane (z-buffer per pixel)."""
    a = _quad(-60, 60, -45, 45, z=lambda x, y: 100 + 0.3 * x)
    b = _quad(-60, 60, -45, 45, z=lambda x, y: 100 - 0.3 * x)
    both = Mesh(vertices=np.concatenate([a.vertices, b.vertices]),
                faces=np.concatenate([a.faces, b.faces + 4]), name="cross")
    K = _K(60, 60, 31.5, 23.5)
    T = _eye()
    T[:, :3, 3] = [[0, 0, 0], [5, 0, 0], [0, 3, 10], [-5, 0, 20]]
    out = _render(_rm(both), T, K)
    for i in range(SYNTH_B):
        pa, za = _plane_hits(T[i], K, np.array([-0.3, 0, 1.0]), 100.0)
        pb, zb = _plane_hits(T[i], K, np.array([0.3, 0, 1.0]), 100.0)
        within = lambda p: (np.abs(p[..., 0]) < 59.9) & (np.abs(p[..., 1]) < 44.9)  # noqa: E731
        clear = (np.abs(za - zb) > 0.05) & within(pa) & within(pb)
        assert clear.sum() > 1000
        np.testing.assert_allclose(out["depth"][i][clear], np.minimum(za, zb)[clear], rtol=1e-5)
        expect_a = za < zb
        got_a = out["face_id"][i] < 2
        np.testing.assert_array_equal(got_a[clear], expect_a[clear])


def _icosphere():
    s = trimesh.creation.icosphere(subdivisions=2, radius=40.0)
    return Mesh(vertices=s.vertices, faces=s.faces, name="icosphere")


def _torus():
    t = trimesh.creation.torus(major_radius=35.0, minor_radius=12.0, major_sections=20,
                               minor_sections=12)
    return Mesh(vertices=t.vertices, faces=t.faces, name="torus")


@pytest.mark.parametrize("make", [_icosphere, _torus])
def test_matches_bruteforce_raycast(make, raycast, poses):
    mesh = make()
    T = poses(mesh, SYNTH_B, seed=3, distance_factor=1.6)
    T[:, 0, 3] += [0, 6, -9, 3]  # off-centre too
    K = _K(75, 62, 30.6, 22.1)
    out = _render(_rm(mesh), T, K)
    for b in range(SYNTH_B):
        depth, face = raycast(mesh.vertices, mesh.faces, T[b], K, SYNTH_HW)
        ref_mask = face >= 0
        assert (out["mask"][b] != ref_mask).mean() < 0.005
        same = (out["face_id"][b] == face) & ref_mask
        assert same.sum() >= 0.99 * ref_mask.sum()
        np.testing.assert_allclose(out["depth"][b][same], depth[same], atol=2e-3)


def test_close_up_large_triangles_drop_no_pixel(raycast):
    """A close-up where triangles span tens of pixels, rasterized with 2x2 windows in chunks of
    64 (many passes of the work loop), equals the brute-force ray caster."""
    mesh = _icosphere()
    T = _eye()
    T[:, 2, 3] = [75, 60, 90, 55]
    T[:, 0, 3] = [0, 10, -15, 5]
    K = _K(40, 40, 31.5, 23.5)
    rm = _rm(mesh)
    out = _render(rm, T, K, tile=2, chunk=64)
    for b in range(SYNTH_B):
        depth, face = raycast(mesh.vertices, mesh.faces, T[b], K, SYNTH_HW)
        assert (out["mask"][b] != (face >= 0)).sum() <= 3
        same = (out["face_id"][b] == face) & (face >= 0)
        assert same.sum() >= 0.99 * (face >= 0).sum()
        np.testing.assert_allclose(out["depth"][b][same], depth[same], atol=2e-3)
    # The default windows and chunks give the same image.
    np.testing.assert_array_equal(_render(rm, T, K)["face_id"], out["face_id"])


def test_near_plane_clips_exactly():
    """A quad spanning from behind the camera to far in front: pixels show it exactly where the
    ray hits it beyond the near plane (no triangle dropped, nothing behind drawn)."""
    quad = _quad(-400, 400, -100, 300, z=lambda x, y: 30.0 + 1.0 * y)
    K = _K(40, 40, 31.5, 23.5)
    T = _eye()
    T[:, 0, 3] = [0, 20, -20, 0]
    near = 40.0
    out = _render(_rm(quad), T, K, near=near)
    for b in range(SYNTH_B):
        p, z = _plane_hits(T[b], K, np.array([0, -1.0, 1.0]), 30.0)
        expect = (z > near) & (np.abs(p[..., 0]) <= 400) & (p[..., 1] >= -100) & (p[..., 1] <= 300)
        assert expect.sum() > 300 and (~expect).sum() > 300
        assert (out["mask"][b] != expect).sum() <= W  # at most the boundary row differs
        both = out["mask"][b] & expect
        np.testing.assert_allclose(out["depth"][b][both], z[both], rtol=1e-4)
        assert np.all(out["depth"][b][out["mask"][b]] > near)


def test_pose_behind_camera_gives_empty_mask():
    mesh = _icosphere()
    T = _eye()
    T[:, 2, 3] = [-300, -100, -41, -1000]
    out = _render(_rm(mesh), T, _K(60, 60, 31.5, 23.5))
    assert not out["mask"].any() and not out["edge"].any()
    assert np.all(out["depth"] == 0) and np.all(out["face_id"] == -1)
    assert np.all(out["xyz"] == 0) and np.all(out["rgb"] == 0)


def test_backface_culling_is_invisible_on_closed_meshes(poses):
    mesh = _icosphere()
    culled, plain = _rm(mesh), _rm(mesh, cull_backfaces=False)
    assert bool(culled.cull_backfaces) and not bool(plain.cull_backfaces)
    T, K = poses(mesh, SYNTH_B, seed=5, distance_factor=1.5), _K(70, 70, 31.5, 23.5)
    a, b = _render(culled, T, K), _render(plain, T, K)
    np.testing.assert_array_equal(a["face_id"], b["face_id"])
    np.testing.assert_array_equal(a["depth"], b["depth"])


def test_edges_are_silhouette_and_creases(raycast):
    """A cube seen corner-on: edge pixels are exactly the foreground pixels with a background
    or other-side 4-neighbour (sides differ by 90 degrees); side interiors have none."""
    box = trimesh.creation.box(extents=(60.0, 60.0, 60.0))
    mesh = Mesh(vertices=box.vertices, faces=box.faces, name="cube")
    from scipy.spatial.transform import Rotation

    T = _eye()
    for b in range(SYNTH_B):
        T[b, :3, :3] = Rotation.from_euler("xyz", [0.5 + 0.2 * b, 0.7, 0.1 * b]).as_matrix()
        T[b, :3, 3] = [2.0 * b, -1.0, 160.0]
    K = _K(55, 58, 31.5, 23.5)
    out = _render(_rm(mesh), T, K)
    n = np.asarray(box.face_normals)
    axis = np.argmax(np.abs(n), -1)
    side_of_face = np.append(2 * axis + (n[np.arange(len(n)), axis] > 0), -1)  # [-1] -> -1
    for b in range(SYNTH_B):
        _, face = raycast(mesh.vertices, mesh.faces, T[b], K, SYNTH_HW)
        side = side_of_face[face]
        pad = np.pad(side, 1, constant_values=-2)  # outside the image: not a neighbour
        nb = [pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]]
        expect = (side >= 0) & np.any([(q != side) & (q != -2) for q in nb], axis=0)
        got = out["edge"][b]
        # Pixel centres exactly on a cube edge may fall to either side.
        tie = side_of_face[out["face_id"][b]] != side
        assert ((got != expect) & ~tie).sum() <= 2
        assert expect.sum() > 40


def test_rgb_grey_without_colours_and_headlight_shading():
    quad = _quad(-60, 60, -45, 45)
    K = _K(60, 60, 31.5, 23.5)
    out = _render(_rm(quad), _eye(), K, ambient=1.0)
    m = out["mask"][0]
    np.testing.assert_allclose(out["rgb"][0][m], 0.7, atol=1e-6)
    # Headlight Lambert: the normal is -z (toward the camera), so |n . v| = cos of the pixel ray.
    lit = _render(_rm(quad), _eye(), K, ambient=0.25)
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    d = np.stack([(u - 31.5) / 60, (v - 23.5) / 60, np.ones_like(u, float)], -1)
    cos = 1 / np.linalg.norm(d, axis=-1)
    np.testing.assert_allclose(lit["rgb"][0][m][:, 0], (0.7 * (0.25 + 0.75 * cos))[m], atol=1e-5)
    np.testing.assert_allclose(np.abs(lit["normal"][0][m]), np.tile([0.0, 0, 1], (m.sum(), 1)),
                               atol=1e-6)


def test_leading_dims_jit_and_vmap(poses):
    mesh = _torus()
    rm = _rm(mesh)
    T = poses(mesh, SYNTH_B, seed=11, distance_factor=1.8).astype(np.float32)
    K = _K(70, 60, 31.5, 23.5).astype(np.float32)
    flat = _render(rm, T, K)
    grid = raster.render(rm, T.reshape(2, 2, 4, 4), K, SYNTH_HW, ALL)
    assert grid["depth"].shape == (2, 2, H, W) and grid["xyz"].shape == (2, 2, H, W, 3)
    np.testing.assert_array_equal(np.asarray(grid["face_id"]).reshape(SYNTH_B, H, W),
                                  flat["face_id"])
    f = jax.jit(jax.vmap(lambda Tb: raster.render(rm, Tb, K, SYNTH_HW, ("depth", "face_id"))))
    mapped = f(jnp.asarray(T.reshape(2, 2, 4, 4)))
    np.testing.assert_array_equal(np.asarray(mapped["face_id"]).reshape(SYNTH_B, H, W),
                                  flat["face_id"])
    np.testing.assert_allclose(np.asarray(mapped["depth"]).reshape(SYNTH_B, H, W), flat["depth"],
                               rtol=1e-6)


def test_inv_intrinsics_matches_numpy():
    rng = np.random.default_rng(0)
    K = np.tile(np.eye(3), (5, 1, 1))
    K[:, 0, 0], K[:, 1, 1] = rng.uniform(50, 900, 5), rng.uniform(50, 900, 5)
    K[:, 0, 1] = rng.normal(0, 2, 5)
    K[:, 0, 2], K[:, 1, 2] = rng.uniform(0, 640, 5), rng.uniform(0, 480, 5)
    np.testing.assert_allclose(np.asarray(raster.inv_intrinsics(jnp.asarray(K, jnp.float32))),
                               np.linalg.inv(K), rtol=1e-5, atol=1e-7)


def test_bad_inputs_raise():
    mesh = _icosphere()
    T = _eye(1)
    T[0, 2, 3] = 200
    K = _K(60, 60, 31.5, 23.5)
    bad_K = K.copy()
    bad_K[0, 0] = 0.0
    with pytest.raises(ValueError, match="fx > 0"):
        render(mesh, T, bad_K, SYNTH_HW)
    singular = T.copy()
    singular[0, :3, :3] = [[1, 0, 0], [0, 1, 0], [0, 0, 0]]
    with pytest.raises(ValueError, match="not a rigid transform"):
        render(mesh, singular, K, SYNTH_HW)
    with pytest.raises(ValueError, match="unknown outputs"):
        render(mesh, T, K, SYNTH_HW, outputs=("depth", "albedo"))
    with pytest.raises(ValueError, match="upper-triangular"):
        check_pose_and_intrinsics(T, K.T)
