"""The contour refiner (issue 36): its pieces against independent references, then the whole.

References: OpenCV's ``remap`` (bilinear sampling), a cube's silhouette derived by hand (the
contour model), float64 central differences (the Gauss-Newton Jacobian), and ground truth of
rasterised scenes (convergence, safety). Tiny contour models (100 views) keep it fast.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from infer import contour_refine
from infer.contour_refine import ContourRefiner
from infer.refine import RefineObject
from threept_jax.geometry.camera import look_at
from threept_jax.pipeline import contour as C
from threept_jax.render.mesh import Mesh, to_raster_mesh
from threept_jax.render.raster import render

HW = (240, 320)
K = np.array([[400.0, 0, 159.5], [0, 400.0, 119.5], [0, 0, 1]], np.float32)


def _cube(side=60.0, color=(0.9, 0.2, 0.1)):
    box = trimesh.creation.box((side, side * 0.7, side * 0.5))
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    return Mesh(v, f, colors=np.tile(color, (len(v), 1)))


def test_bilinear_matches_opencv_remap():
    import cv2

    rng = np.random.default_rng(0)
    img = rng.random((17, 23, 3)).astype(np.float32)
    uv = np.stack([rng.uniform(0, 22, 200), rng.uniform(0, 16, 200)], -1).astype(np.float32)
    ours, inside = C._bilinear(jnp.asarray(img), jnp.asarray(uv))
    ref = cv2.remap(img, uv[:, 0:1].copy(), uv[:, 1:2].copy(), cv2.INTER_LINEAR)[:, 0]
    np.testing.assert_allclose(np.asarray(ours), ref, atol=1e-4)
    assert np.asarray(inside).all()
    _, outside = C._bilinear(jnp.asarray(img), jnp.array([[-0.5, 3.0], [22.5, 3.0]]))
    assert not np.asarray(outside).any()


def test_contour_model_of_a_box_seen_along_its_axes():
    """A 60 x 42 x 30 mm box seen along +z: the silhouette is the 60 x 42 rectangle, so every
    contour point has |x| = 30 or |y| = 21 and its outward normal is the matching axis."""
    model = C.contour_model([_cube()], num_views=100, num_points=64)
    d = np.asarray(model.directions[0])
    k = int(np.argmax(d @ np.array([0, 0, 1.0])))
    assert d[k, 2] > 0.98
    # The Fibonacci view nearest +z is a few degrees off: allow the box's tilt in the tolerance.
    p, n = np.asarray(model.points[0, k]), np.asarray(model.normals[0, k])
    tol = 30 * np.sin(np.arccos(d[k, 2])) + 1.0
    on_x = np.abs(np.abs(p[:, 0]) - 30) < tol
    on_y = np.abs(np.abs(p[:, 1]) - 21) < tol
    assert np.all(on_x | on_y)
    sx = on_x & ~on_y
    np.testing.assert_allclose(np.abs(n[sx, 0]), 1.0, atol=0.1)
    assert np.all(np.sign(n[sx, 0]) == np.sign(p[sx, 0]))  # outward
    assert np.asarray(model.valid[0]).all()
    np.testing.assert_allclose(float(model.radius[0]), np.linalg.norm([30, 21, 15]), rtol=1e-3)


def test_offset_jacobian_matches_central_differences():
    """a = d(offset along the projected normal)/d(6 pose parameters), against float64 central
    differences of the projected point moved by the same parametrisation."""
    rng = np.random.default_rng(1)
    pts = rng.normal(0, 20, (5, 3))
    nrm = rng.normal(0, 1, (5, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    center, radius = np.array([1.0, -2.0, 3.0]), 40.0
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    T[:3, 3] = [10, -5, 400]
    img = jnp.zeros((240, 320, 3))
    ev = C.line_evidence(img, jnp.asarray(K), jnp.asarray(T, jnp.float32),
                         jnp.asarray(pts, jnp.float32), jnp.asarray(nrm, jnp.float32),
                         jnp.ones(5, bool), jnp.asarray(center, jnp.float32),
                         jnp.float32(radius), jnp.float32(0.05), jnp.int32(0),
                         -jnp.ones((4, 4), jnp.int32), jnp.zeros((4, 4)), C.ContourSettings())
    Kd = K.astype(np.float64)

    def proj(delta):
        dR = Rotation.from_rotvec(delta[:3] / radius).as_matrix()
        X = center + (pts - center) @ dR.T + delta[3:]
        Xc = X @ T[:3, :3].T + T[:3, 3]
        return (Xc @ Kd.T)[:, :2] / Xc[:, 2:3]

    # The line direction: the projected normal at the pose.
    eps = 1e-4
    base = proj(np.zeros(6))
    Xc = pts @ T[:3, :3].T + T[:3, 3]
    tip = (Xc + eps * nrm @ T[:3, :3].T) @ Kd.T
    n2 = tip[:, :2] / tip[:, 2:3] - base
    n2 /= np.linalg.norm(n2, axis=1, keepdims=True)
    num = np.zeros((5, 6))
    for i in range(6):
        e = np.zeros(6)
        e[i] = 1e-3
        num[:, i] = np.sum((proj(e) - proj(-e)) / 2e-3 * n2, -1)
    np.testing.assert_allclose(np.asarray(ev.a), num, rtol=2e-3, atol=2e-4)



def test_offset_from_the_start_follows_the_step_parametrisation():
    """The prior's offset of a pose from its start: zero at the start; after one step delta
    made as the update makes it (turn about the centre by delta[:3] / radius, then shift the
    centre by delta[3:], in the object frame; float64 SciPy), exactly delta's turn and the
    shift seen from the moved pose's frame (dR^T delta[3:])."""
    center, radius = np.array([4.0, -3.0, 10.0]), 50.0
    start = np.eye(4)
    start[:3, :3] = Rotation.from_rotvec([0.4, 0.1, -0.7]).as_matrix()
    start[:3, 3] = [20.0, -10.0, 600.0]

    def offset(T):
        return np.asarray(C._offset(jnp.asarray(T[None], jnp.float32),
                                    jnp.asarray(start[None], jnp.float32),
                                    jnp.asarray(center[None], jnp.float32),
                                    jnp.asarray([radius], jnp.float32)))[0]

    rng = np.random.default_rng(3)
    for scale in (1e-2, 1.0):
        delta = rng.normal(0, scale, 6)
        dR = Rotation.from_rotvec(delta[:3] / radius).as_matrix()
        moved = start.copy()
        moved[:3, :3] = start[:3, :3] @ dR
        moved[:3, 3] = start[:3, 3] + start[:3, :3] @ (center - dR @ center + delta[3:])
        got = offset(moved)
        np.testing.assert_allclose(got[:3], delta[:3], atol=1e-3)
        np.testing.assert_allclose(got[3:], dR.T @ delta[3:], atol=2e-3)
    np.testing.assert_allclose(offset(start), 0.0, atol=1e-4)
    with pytest.raises(ValueError, match="must be >= 0"):
        C.ContourSettings(prior=-0.1)


def test_a_refinement_that_moves_out_of_reach_keeps_its_start():
    """within_reach against hand-made poses: turns about the object's centre (off the origin,
    so the translation changes too) of 29 and 31 degrees against the 30 degree reach, and
    shifts of the centre by 0.95 and 1.05 diameters against the one-diameter reach."""
    settings = C.ContourSettings()
    center, radius = np.array([10.0, -20.0, 5.0]), 40.0
    start = np.eye(4)
    start[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()
    start[:3, 3] = [5.0, 0.0, 600.0]

    def turned(deg):
        T = start.copy()
        c = start[:3, :3] @ center + start[:3, 3]
        T[:3, :3] = Rotation.from_rotvec(np.radians(deg) * np.array([0.6, 0.0, 0.8])
                                         ).as_matrix() @ start[:3, :3]
        T[:3, 3] = c - T[:3, :3] @ center  # the centre stays where it was
        return T

    def shifted(diameters):
        T = start.copy()
        T[:3, 3] += diameters * 2 * radius * np.array([0.0, 0.6, -0.8])
        return T

    poses = np.stack([start, turned(29.0), turned(31.0), shifted(0.95), shifted(1.05)])
    ok = C.within_reach(jnp.asarray(poses, jnp.float32), jnp.asarray(np.stack([start] * 5),
                        jnp.float32), jnp.full((5, 3), center, jnp.float32),
                        jnp.full(5, radius, jnp.float32), settings)
    assert np.asarray(ok).tolist() == [True, True, False, True, False]


def _scene(mesh, views, seed=0):
    """``mesh`` on a noisy grey background seen by ``views`` cameras 400 mm away."""
    rng = np.random.default_rng(seed)
    T_gt = np.eye(4)
    T_gt[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    eyes = np.array([[0, -60, 400], [346, 0, -200], [-346, 60, -200]], np.float64)[:views]
    T_cw = np.stack([np.asarray(look_at(e, np.zeros(3), (0, 1.0, 0)), np.float64) for e in eyes])
    rm = to_raster_mesh(mesh)
    images = []
    for T in T_cw:
        out = render(rm, (T @ T_gt).astype(np.float32), K, HW, ("rgb", "mask"), ambient=0.6)
        bg = np.clip(0.45 + 0.08 * rng.standard_normal(HW + (3,)), 0, 1)
        img = np.where(np.asarray(out["mask"])[..., None], np.asarray(out["rgb"]), bg)
        images.append(np.round(img * 255).astype(np.uint8))
    return np.stack(images), np.tile(K, (views, 1, 1)), T_cw, T_gt


def _jitter(T, deg, mm, rng):
    out = T.copy()
    axis = rng.standard_normal(3)
    out[:3, :3] = Rotation.from_rotvec(np.radians(deg) * axis / np.linalg.norm(axis)
                                       ).as_matrix() @ T[:3, :3]
    step = rng.standard_normal(3)
    out[:3, 3] += mm * step / np.linalg.norm(step)
    return out


def _err(T, T_gt):
    dR = T[:3, :3].T @ T_gt[:3, :3]
    return (np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))),
            np.linalg.norm(T[:3, 3] - T_gt[:3, 3]))


@pytest.fixture(scope="module")
def refiner():
    mesh = _cube()
    r = ContourRefiner([RefineObject(1, mesh, np.eye(4)[None])])
    return r, mesh


def test_three_views_converge_and_one_view_never_gets_worse(refiner):
    r, mesh = refiner
    rng = np.random.default_rng(3)
    images, Ks, T_cw, T_gt = _scene(mesh, 3)
    starts = [_jitter(T_gt, 10.0, 15.0, rng) for _ in range(4)]
    traces = contour_refine.TRACES[0]
    out = [r(list(images), Ks, T_cw, [1], [s])[0] for s in starts]
    after = np.array([_err(o.T_world_obj, T_gt) for o in out])
    before = np.array([_err(s, T_gt) for s in starts])
    assert np.median(after[:, 0]) < 1.5 and np.median(after[:, 1]) < 3.0, (before, after)
    # One view: rotation improves from every start, and no start ends worse.
    one = [r(list(images[:1]), Ks[:1], T_cw[:1], [1], [s])[0] for s in starts]
    after1 = np.array([_err(o.T_world_obj, T_gt) for o in one])
    assert np.all(after1[:, 0] <= before[:, 0] + 0.5), (before, after1)
    assert np.median(after1[:, 0]) < 0.6 * np.median(before[:, 0])
    # Scores: the refined pose's contour score beats the start's; masks are the silhouettes.
    assert all(0.0 <= o.score <= 1.0 for o in out)
    assert out[0].masks[0].shape == HW and out[0].masks[0].sum() > 500
    assert contour_refine.TRACES[0] - traces <= 2  # at most one compilation per view count
    # Another refiner of the same object set shares the compilation.
    again = ContourRefiner([RefineObject(1, mesh, np.eye(4)[None])])
    traces = contour_refine.TRACES[0]
    np.testing.assert_array_equal(again(list(images), Ks, T_cw, [1], [starts[0]])[0].T_world_obj,
                                  out[0].T_world_obj)
    assert contour_refine.TRACES[0] == traces


def test_no_object_in_the_image_returns_the_start(refiner):
    """A grey image: nothing to follow; the refined pose must not score higher, so the start
    comes back unchanged. A pose fully outside the image: no valid line, start returned."""
    r, _ = refiner
    grey = np.full(HW + (3,), 128, np.uint8)
    T = np.eye(4)
    T[2, 3] = 400.0
    out = r([grey], K[None], None, [1], [T])[0]
    np.testing.assert_allclose(out.T_world_obj, T, atol=1e-4)
    far = T.copy()
    far[0, 3] = 5000.0  # far right of the image
    out = r([grey], K[None], None, [1], [far])[0]
    np.testing.assert_allclose(out.T_world_obj, far, atol=1e-3)
    assert out.score == 0.0


def test_bad_input_is_refused_with_the_reason(refiner):
    r, _ = refiner
    img = np.zeros(HW + (3,), np.uint8)
    T = np.eye(4)
    T[2, 3] = 400.0
    bad = T.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="not finite"):
        r([img], K[None], None, [1], [bad])
    with pytest.raises(KeyError, match="not in this refiner's object set"):
        r([img], K[None], None, [7], [T])
    assert r([img], K[None], None, [], []) == []
    with pytest.raises(ValueError, match="face"):  # a mesh without faces never reaches it
        Mesh(np.zeros((3, 3)), np.zeros((0, 3), np.int64))


def test_api_refine_with_the_contour_refiner(refiner):
    """``infer.load(refiner="contour")`` + ``infer.refine``: the public path."""
    import infer
    from infer.api import Models

    _, mesh = refiner
    models = infer.load(None, refiner="contour", cache_dir=None)
    assert isinstance(models, Models) and isinstance(models.refiner, C.ContourSettings)
    rng = np.random.default_rng(5)
    images, Ks, T_cw, T_gt = _scene(mesh, 3, seed=2)
    start = _jitter(T_gt, 8.0, 10.0, rng)
    cams = [infer.Camera(Ks[v], T_cam_world=T_cw[v]) for v in range(3)]
    out = infer.refine(list(images), cams, [RefineObject(1, mesh, np.eye(4)[None])],
                       [(1, start)], models)
    assert _err(out[0].T_world_obj, T_gt)[0] < 0.5 * _err(start, T_gt)[0]
    assert set(out[0].masks) == {0, 1, 2}
    jax.clear_caches()


def test_contours_are_cached_per_mesh_and_a_damaged_file_is_rebuilt(tmp_path, monkeypatch):
    import infer.contour_refine as CR

    calls = []
    real = CR.mesh_contours

    def counted(mesh, **kw):
        calls.append(mesh)
        return real(mesh, num_views=20, num_points=16)

    monkeypatch.setattr(CR, "mesh_contours", counted)
    a = CR._cached_contours(_cube(), tmp_path)
    b = CR._cached_contours(_cube(), tmp_path)
    assert len(calls) == 1
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    (f,) = tmp_path.glob("*.npz")
    f.write_bytes(b"damaged")
    c = CR._cached_contours(_cube(), tmp_path)
    assert len(calls) == 2 and np.array_equal(c["points"], a["points"])
    CR._cached_contours(_cube(side=50.0), tmp_path)  # another mesh, another file
    assert len(calls) == 3 and len(list(tmp_path.glob("*.npz"))) == 2


def test_turns_are_cached_per_mesh_and_symmetries(tmp_path, monkeypatch):
    """The near-symmetric turns are found once per mesh and declared symmetries: the box's
    three half-turns (by hand), none once they are declared, each set its own file."""
    import infer.contour_refine as CR

    calls = []
    real = CR.near_symmetry_turns

    def counted(*a, **kw):
        calls.append(1)
        return real(*a, **kw)

    monkeypatch.setattr(CR, "near_symmetry_turns", counted)
    box = RefineObject(1, _cube(), np.eye(4)[None])
    a = CR._cached_turns(box, tmp_path)
    b = CR._cached_turns(box, tmp_path)
    assert len(calls) == 1 and a.shape == (3, 4, 4)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(np.abs(np.einsum("mii->mi", a[:, :3, :3])),
                               np.ones((3, 3)), atol=1e-9)  # diag(+-1): about the box's axes
    declared = RefineObject(1, _cube(), np.concatenate([np.eye(4)[None], a]))
    assert len(CR._cached_turns(declared, tmp_path)) == 0
    assert len(calls) == 2 and len(list(tmp_path.glob("*.npz"))) == 2
