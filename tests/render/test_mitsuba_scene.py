"""Mitsuba backend: square-pixel resampling for fx != fy, the path-traced scene builder, locks."""

import contextlib
import threading

import numpy as np
import pytest
import trimesh

from threept_jax.geometry.camera import crop_intrinsics
from threept_jax.render import Mesh, crop_and_resize, mitsuba_backend, raster, to_raster_mesh
from threept_jax.render.mitsuba_backend import (
    Material,
    MitsubaRenderer,
    MitsubaScene,
    load_mitsuba,
    resample_square_render,
    square_pixel_camera,
)

HW = (48, 64)


def _K(fx, fy, cx, cy):
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])


def _ell():
    """An L-shaped block (asymmetric, so any flip or offset of the image shows)."""
    a = trimesh.creation.box(extents=(60, 20, 20))
    b = trimesh.creation.box(extents=(20, 50, 20))
    b.apply_translation((-20, 35, 0))
    m = trimesh.util.concatenate([a, b])
    return Mesh(vertices=m.vertices, faces=m.faces, name="ell")


def _look(eye, target=(0, 0, 0), up=(0, 0, 1)):
    from threept_jax.geometry.camera import look_at

    return np.asarray(look_at(np.asarray(eye, np.float32), np.asarray(target, np.float32),
                              np.asarray(up, np.float32)), np.float64)


@pytest.mark.parametrize("K", [_K(80, 80, 31.5, 23.5), _K(90, 70, 30.2, 25.7),
                               _K(60, 85, 35.0, 20.0)])
def test_square_pixel_camera_crops_back_to_K(K):
    K_sq, hw_sq, box = square_pixel_camera(K, HW)
    assert K_sq[0, 0] == K_sq[1, 1] == max(K[0, 0], K[1, 1])
    np.testing.assert_allclose(np.asarray(crop_intrinsics(K_sq, box, HW)), K, rtol=1e-6)  # float32
    assert box[0] >= 0 and box[1] >= 0 and box[2] <= hw_sq[1] and box[3] <= hw_sq[0]


@pytest.mark.parametrize("K", [_K(90, 70, 30.2, 25.7), _K(60, 85, 35.0, 20.0)])
def test_square_render_resamples_as_crop_and_resize(K):
    """The host resampling of a square-pixel render (SciPy, float64) against the JAX crop."""
    K_sq, hw_sq, box = square_pixel_camera(K, HW)
    img = np.random.default_rng(0).random((*hw_sq, 3)).astype(np.float32)
    got = resample_square_render(img, box, HW)
    assert got.shape == (*HW, 3) and got.dtype == np.float32
    np.testing.assert_allclose(got, np.asarray(crop_and_resize(img, box, HW)), atol=1e-5)


@pytest.mark.parametrize("K", [_K(80, 80, 26.5, 27.0), _K(95, 70, 29.2, 26.7),
                               _K(70, 95, 34.1, 21.4)])
def test_path_traced_view_matches_ray_cast_silhouette(K):
    """A black object against a bright environment: the path-traced (sensor, resampled when
    fx != fy) silhouette equals the exact pixel-centre ray-cast mask."""
    scene = MitsubaScene()
    T_world_obj = np.eye(4)
    T_world_obj[:3, 3] = [5, -3, 0]
    scene.add_object(_ell(), T_world_obj, Material(color=(0.0, 0.0, 0.0)))
    scene.set_environment((1.0, 1.0, 1.0))
    T_cam_world = _look(eye=(80, -110, 95), target=(0, 0, 5))
    out = scene.render(K, T_cam_world, HW, spp=16, seed=1, linear=True)
    dark = out["rgb"].mean(-1) < 0.5
    mask = out["mask"]
    assert mask.sum() > 300
    iou = (dark & mask).sum() / (dark | mask).sum()
    assert iou > 0.93, iou
    # Edge pixels aside (anti-aliased), the two agree.
    inner = mask.copy()
    for axis in (0, 1):
        inner &= np.roll(mask, 1, axis) & np.roll(mask, -1, axis)
    assert dark[inner].all()


def _plane_depth(K, T_cam_world):
    """Depth z [H, W] of the world plane z = 0 along each pixel ray (hand-derived)."""
    u, v = np.meshgrid(np.arange(HW[1], dtype=float), np.arange(HW[0], dtype=float))
    d_cam = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
    R, t = T_cam_world[:3, :3], T_cam_world[:3, 3]
    d_world = d_cam @ R  # R^T d
    C = -R.T @ t
    z = -C[2] / d_world[..., 2]
    return C + z[..., None] * d_world, z


def test_scene_instances_depth_and_object_coordinates_match_jax():
    """Two objects on a ground plane: instance ids, depth and per-object coordinates from the
    scene agree with single-object renders of the JAX rasterizer."""
    ell = _ell()
    s = trimesh.creation.icosphere(subdivisions=2, radius=25.0)
    red = np.tile([0.9, 0.1, 0.1], (len(s.vertices), 1))
    ball = Mesh(vertices=s.vertices, faces=s.faces, colors=red)
    Ta, Tb = np.eye(4), np.eye(4)
    Ta[:3, 3] = [-30, 0, 10]
    from scipy.spatial.transform import Rotation

    Tb[:3, :3] = Rotation.from_euler("z", 0.7).as_matrix()
    Tb[:3, 3] = [40, 25, 25]
    scene = MitsubaScene()
    ids = [scene.add_object(ell, Ta, Material("plastic", roughness=0.2)),
           scene.add_object(ball, Tb, Material("diffuse"))]
    assert ids == [1, 2]
    metal = Material("conductor", color=(0.8, 0.8, 0.8), roughness=0.4)
    scene.set_ground(size=600.0, material=metal)
    scene.set_environment((0.3, 0.3, 0.3))
    scene.add_point_light((0, 0, 400), (2e5, 2e5, 2e5))
    T_light = _look(eye=(0, -200, 300))
    scene.add_area_light(np.linalg.inv(T_light), (100, 100), (5, 5, 5))
    K = _K(70, 60, 32.3, 22.8)
    T_cw = _look(eye=(60, -220, 180), target=(0, 10, 10))
    out = scene.render(K, T_cw, HW, spp=8, seed=0)
    assert out["rgb"].shape == HW + (3,) and np.isfinite(out["rgb"]).all()
    assert out["rgb"].min() >= 0 and out["rgb"].max() <= 1
    depths, xyzs = [], []
    for mesh, T in ((ell, Ta), (ball, Tb)):
        r = raster.render(to_raster_mesh(mesh, face_bucket=512), (T_cw @ T)[None], K, HW,
                          ("depth", "xyz", "mask"))
        d = np.asarray(r["depth"][0])
        depths.append(np.where(d > 0, d, np.inf))
        xyzs.append(np.asarray(r["xyz"][0]))
    depths = np.stack(depths)
    expect = np.where(np.isfinite(depths.min(0)), np.argmin(depths, 0) + 1, 0)
    inst = out["instance"]
    for k in (1, 2):
        iou = ((inst == k) & (expect == k)).sum() / ((inst == k) | (expect == k)).sum()
        assert iou > 0.97
    agree = (inst == expect) & (inst > 0)
    np.testing.assert_allclose(out["depth"][agree], depths.min(0)[agree], atol=0.05)
    xyz_ref = np.where((expect == 1)[..., None], xyzs[0], xyzs[1])
    np.testing.assert_allclose(out["xyz"][agree], xyz_ref[agree], atol=0.05)
    assert out["mask"].sum() == (inst > 0).sum() and np.all(out["xyz"][inst == 0] == 0)
    # The ground fills the rest of the view: its depth is that of the z = 0 plane.
    p_ground, z_ground = _plane_depth(K, T_cw)
    ground = (inst == 0) & (np.abs(p_ground[..., :2]) < 299).all(-1) & (z_ground > 0)
    assert ground.sum() > 1000
    np.testing.assert_allclose(out["depth"][ground], z_ground[ground], rtol=1e-4)
    off = (inst == 0) & (np.abs(p_ground[..., :2]) > 301).any(-1)
    assert off.sum() > 50 and np.all(out["depth"][off] == 0)  # rays that escape
    # The ball is diffuse red: red dominates its pixels.
    ball_rgb = out["rgb"][inst == 2]
    assert (ball_rgb[:, 0] > ball_rgb[:, 1] + 0.05).mean() > 0.8


def test_renderer_lock_makes_threads_safe():
    mesh = _ell()
    r = MitsubaRenderer(mesh)
    T = np.tile(_look(eye=(100, -120, 90)), (3, 1, 1))
    K = _K(70, 60, 31.5, 23.5)
    ref = r.render(T, K, HW, ("depth", "face_id"))
    results = [None] * 4

    def work(i):
        results[i] = r.render(T, K, HW, ("depth", "face_id"))

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    for res in results:
        np.testing.assert_array_equal(res["face_id"], ref["face_id"])
        np.testing.assert_array_equal(res["depth"], ref["depth"])


def test_wavefront_renders_equal_drjits_symbolic_renders_on_two_threads(monkeypatch):
    """The scene's renders run in Dr.Jit's wavefront mode (``mitsuba_backend._wavefront``);
    Dr.Jit's default symbolic mode (one kernel per scene) is the reference. Colour, the
    denoiser's normal and albedo and the geometry outputs must be bit-identical on two threads
    (the albedo-then-normal AOV order lost the normal's x component on several pixels)."""
    import drjit as dr

    load_mitsuba()
    threads = dr.thread_count()
    dr.set_thread_count(2)
    try:
        wavefront, symbolic = _render_both_ways(monkeypatch)
    finally:
        dr.set_thread_count(threads)
    for (key, a), b in zip(wavefront.items(), symbolic.values()):
        np.testing.assert_array_equal(a, b, err_msg=key)
    assert np.abs(wavefront["aux_normal"]).max() > 0.5  # the normals are there


def test_only_small_renders_run_in_wavefront_mode_and_the_flags_come_back():
    import drjit as dr

    load_mitsuba()
    flags = (dr.JitFlag.SymbolicCalls, dr.JitFlag.SymbolicLoops)
    before = [dr.flag(f) for f in flags]
    with mitsuba_backend._wavefront(mitsuba_backend.WAVEFRONT_MAX_LANES):
        assert [dr.flag(f) for f in flags] == [False, False]
    with mitsuba_backend._wavefront(mitsuba_backend.WAVEFRONT_MAX_LANES + 1):
        assert [dr.flag(f) for f in flags] == before
    assert [dr.flag(f) for f in flags] == before


def _render_both_ways(monkeypatch):
    """One scene rendered in wavefront mode, then in symbolic mode: the outputs and the
    denoiser's inputs (colour, albedo, normal) of each."""
    mesh = _ell()
    scene = MitsubaScene(max_depth=3)
    for i, kind in enumerate(("diffuse", "plastic", "conductor")):
        T = np.eye(4)
        T[:3, 3] = [70.0 * (i - 1), 0, 0]
        scene.add_object(mesh, T, Material(kind=kind, color=(0.2 + 0.3 * i, 0.5, 0.3)))
    scene.add_point_light((150, -100, 300), (4e5, 4e5, 4e5))
    scene.set_environment((0.4, 0.5, 0.6))
    K, T_cw, outputs = _K(60, 60, 31.5, 23.5), _look(eye=(0, -220, 260)), ("rgb", "normal", "xyz")
    seen = []

    def denoise(colour, albedo, normal):
        seen.append({"aux_colour": colour, "aux_albedo": albedo, "aux_normal": normal})
        return colour

    monkeypatch.setattr("threept_jax.render.denoise.denoise", denoise)
    wavefront = scene.render(K, T_cw, HW, spp=4, seed=3, outputs=outputs, denoise=True)
    monkeypatch.setattr(mitsuba_backend, "_wavefront", contextlib.nullcontext)
    symbolic = scene.render(K, T_cw, HW, spp=4, seed=3, outputs=outputs, denoise=True)
    return wavefront | seen[0], symbolic | seen[1]


def test_missing_libllvm_names_the_fix(monkeypatch):
    import drjit

    monkeypatch.setattr(drjit, "has_backend", lambda backend: False)
    with pytest.raises(RuntimeError, match="apt-get install libllvm19"):
        load_mitsuba("llvm_ad_rgb")


def test_material_validation():
    with pytest.raises(ValueError, match="kind"):
        Material("velvet")
    with pytest.raises(ValueError, match="roughness"):
        Material("plastic", roughness=0.0)
    scene = MitsubaScene()
    with pytest.raises(ValueError, match="rigid"):
        scene.add_object(_ell(), np.diag([2.0, 2.0, 2.0, 1.0]))
    with pytest.raises(ValueError, match="spp"):
        scene.add_object(_ell(), np.eye(4))
        scene.render(_K(70, 60, 31.5, 23.5), _look(eye=(100, -120, 90)), HW, spp=0)
