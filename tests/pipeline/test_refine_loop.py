"""The 3PT-R inference loop (issue 15, section 1) with the oracle network.

Scenes: a T-LESS mesh painted with its object coordinates (``testing.refiner_oracle``) rendered
into full images at ambient 1; the loop crops them itself. Pose errors are float64 NumPy/SciPy.

The loop's crops use ``antialias=1`` here: the oracle reads a pixel's colour as the coordinate
seen at its centre, which an area-averaged crop is not at creases and silhouettes (a trained
network learns the training crops' antialiasing; the oracle cannot), and the images are 640 x
480 so that bilinear sampling of them is close to a point sample at the 32 px crops. Antialiasing
itself is checked against a block mean.
"""

import dataclasses
import warnings

import jax
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from infer.refine import RefineObject, SceneRefiner
from threept_jax.data.refiner_input import RefinerMeshes
from threept_jax.geometry.camera import look_at
from threept_jax.models.configs import get_refiner_config
from threept_jax.pipeline.refine_loop import (
    LoopSettings,
    antialiased_crops,
    pad_to_bin,
    paste_masks,
    refine_instances,
)
from threept_jax.pipeline.refinement import RefineSettings
from threept_jax.render.mesh import Mesh, load_mesh, prepare_mesh, to_raster_mesh
from threept_jax.render.raster import render
from threept_jax.testing.refiner_oracle import COLOR_SCALE, make_oracle, xyz_colored

MESH = "/work/shared/meshes/bop/tless/models/obj_000018.ply"  # no symmetry, 111 mm
CROP = MAP = 32
HW = (480, 640)
K_FULL = np.array([[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]], np.float32)
S2 = np.diag([-1.0, -1.0, 1.0, 1.0])  # the box's 2-fold symmetry about its z axis
SETTINGS = RefineSettings(num_matches=256, ambient=1.0)
LOOP = LoopSettings(antialias=1)
ORACLE = make_oracle(MAP)
TRACES = []


def _loop(network, *args, loop):
    TRACES.append(args[-1].shape)  # runs only while tracing
    return refine_instances(network, *args, crop_size=CROP, output_size=MAP, settings=SETTINGS,
                            loop=loop)


LOOP_JIT = jax.jit(_loop, static_argnames=("network", "loop"))


def _box_mesh():
    """A 60 x 40 x 30 mm box whose colours are invariant under S2: each face (all on one side of
    x = 0 after one subdivision) is coloured with the object coordinates of its x >= 0 copy."""
    tm = trimesh.creation.box(extents=(60.0, 40.0, 30.0)).subdivide()
    tri = np.asarray(tm.vertices)[np.asarray(tm.faces)]  # [F, 3, 3], unshared corners
    assert np.all((tri[..., 0] <= 1e-9).all(1) | (tri[..., 0] >= -1e-9).all(1))
    canon = np.where((tri[:, :, 0].mean(1) < 0)[:, None, None], tri * [-1, -1, 1], tri)
    mesh = Mesh(vertices=tri.reshape(-1, 3), faces=np.arange(tri.size // 3).reshape(-1, 3),
                name="box")
    return mesh.replace(colors=0.5 + (canon.reshape(-1, 3) - mesh.center)
                        / (COLOR_SCALE * mesh.radius))


@pytest.fixture(scope="module")
def meshes():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the T-LESS file repeats faces
        tless = xyz_colored(prepare_mesh(load_mesh(MESH), max_faces=1024))
    return tless, _box_mesh(), RefinerMeshes.from_meshes({18: tless, 99: _box_mesh()})


def _pose(R, center_world, mesh):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = center_world - R @ mesh.center
    return T


def _rot(deg, seed):
    axis = np.random.default_rng(seed).normal(size=3)
    return Rotation.from_rotvec(np.deg2rad(deg) * axis / np.linalg.norm(axis)).as_matrix()


def _image(poses, meshes, T_cw):
    """uint8 [H, W, 3]: the meshes at T_world_obj poses, nearest surface wins."""
    rgb, depth = np.zeros(HW + (3,), np.float32), np.full(HW, np.inf)
    for T, m in zip(poses, meshes):
        out = render(to_raster_mesh(m), T_cw @ T, K_FULL, HW, ("rgb", "depth", "mask"),
                     ambient=1.0)
        d = np.where(np.asarray(out["mask"]), np.asarray(out["depth"]), np.inf)
        near = d < depth
        rgb[near], depth = np.asarray(out["rgb"])[near], np.minimum(depth, d)
    return np.round(rgb * 255).astype(np.uint8)


def _hypotheses(T, mesh, seed):
    """K = 4, best first: 15 degrees and 15 mm off, then 90, 120 and 150 degrees off."""
    out = []
    for i, deg in enumerate((15, 90, 120, 150)):
        c = T[:3, :3] @ mesh.center + T[:3, 3] + ([3.0, -2.0, 14.5] if i == 0 else 0.0)
        out.append(_pose(T[:3, :3] @ _rot(deg, seed + i), c, mesh))
    return np.stack(out)


def _errors(T, T_gt, symmetries=None):
    """(degrees, mm) of T against T_gt up to the symmetries (float64)."""
    errs = []
    for S in [np.eye(4)] if symmetries is None else symmetries:
        G = T_gt @ S
        deg = np.rad2deg(Rotation.from_matrix(T[:3, :3] @ G[:3, :3].T).magnitude())
        errs.append((deg, np.linalg.norm(T[:3, 3] - G[:3, 3])))
    return min(errs)


@pytest.fixture(scope="module")
def scene(meshes):
    """Two poses of the T-LESS mesh side by side in one 640 x 480 view, K = 4 each."""
    tless = meshes[0]
    T_gt = np.stack([_pose(Rotation.random(random_state=s).as_matrix(), [dx, 0.0, 400.0], tless)
                     for s, dx in ((1, -80.0), (2, 80.0))])
    image = _image(T_gt, [tless, tless], np.eye(4))
    hyps = np.stack([_hypotheses(T_gt[0], tless, 10), _hypotheses(T_gt[1], tless, 20)])
    args = dict(mesh_index=np.zeros(2, np.int32), images=image[None], Ks=K_FULL[None],
                T_cam_world=np.eye(4, dtype=np.float32)[None], hypotheses=hyps,
                symmetries=np.tile(np.eye(4), (2, 1, 1, 1)), symmetry_mask=np.ones((2, 1), bool),
                instance_mask=np.ones(2, bool), view_mask=np.ones((2, 1), bool))
    return T_gt, args


def _in_three_views(args):
    """One view's ``args`` as the three-view program sees them: the view and two masked copies
    (``view_mask`` False: no weight in PnP, not in the score), so that this module's one-view
    scenes and its three-view scene share one compilation (about 20 s on 2 cores). The
    program of one view itself runs in the API tests (test_refine_api.py, test_track_cli.py)."""
    out = dict(args)
    for k in ("images", "Ks", "T_cam_world"):
        out[k] = np.repeat(np.asarray(args[k]), 3, 0)
    out["view_mask"] = np.asarray(args["view_mask"]) & (np.arange(3) == 0)
    return out


ORDER = ("mesh_index", "images", "Ks", "T_cam_world", "hypotheses", "symmetries",
         "symmetry_mask", "instance_mask", "view_mask")


def _run(meshes, args, loop=LOOP):
    return LOOP_JIT(ORACLE, meshes[2].stacked, *[args[k] for k in ORDER], loop=loop)


def _pad(args, garbage: bool):
    """The instances of ``args`` padded to the 4-bin: padding rows of NaN / 7 (``garbage``)
    or copies of instance 0, all with ``instance_mask`` False."""
    n = len(args["hypotheses"])
    out = {}
    for k, v in args.items():
        v = np.asarray(v)
        if k in ("images", "Ks", "T_cam_world"):
            out[k] = v
            continue
        fill = (np.full((4 - n,) + v.shape[1:], np.nan if v.dtype.kind == "f" else 7, v.dtype)
                if garbage else np.repeat(v[:1], 4 - n, 0))
        out[k] = np.concatenate([v, fill.astype(v.dtype)])
    out["instance_mask"] = np.arange(4) < n
    return out


@pytest.fixture(scope="module")
def result(meshes, scene):
    """The scene's 2 instances, padded to 4, in the three-view program (one compilation for
    this, the padding test and the three-view test)."""
    return _run(meshes, _pad(_in_three_views(scene[1]), garbage=False))


def test_two_instances_converge_in_one_view(scene, result):
    """15 degrees and 15 mm off among far hypotheses, K = 4 -> 2 -> 1: within 1 mm, 0.2 deg."""
    T_gt, args = scene
    table = np.array([[_errors(np.asarray(result.history[n, i], np.float64), T_gt[n])
                       for i in range(5)] for n in range(2)])
    msg = f"(deg, mm) per instance and iteration:\n{np.round(table, 3)}"
    assert np.all(table[:, -1, 0] < 0.2) and np.all(table[:, -1, 1] < 1.0), msg
    np.testing.assert_allclose(result.poses, result.history[:, -1])
    np.testing.assert_allclose(result.history[:2, 0], args["hypotheses"][:, 0], atol=1e-6)
    assert result.hypotheses.shape == (4, 2, 4, 4) and result.hypothesis_scores.shape == (4, 2)
    np.testing.assert_array_equal(result.scores[:2], result.hypothesis_scores[:2, 0])
    # The refiner's mask of the final pose, pasted into the image, covers the object (each
    # instance on its half of the image).
    fg = args["images"][0].sum(-1) > 0
    for n in range(2):
        pasted = paste_masks(result.mask_logits[n], result.boxes[n], HW)[0]
        truth = fg & ((np.arange(HW[1]) < HW[1] // 2) == (n == 0))[None]
        assert (pasted & truth).sum() / (pasted | truth).sum() > 0.9


def test_scene_refiner_runs_a_network_function(meshes, scene):
    """``SceneRefiner`` with a parameter-free network function (the oracle, as bench/heldout.py
    uses it for its upper bound) refines like the bare loop: one instance of the scene, one
    iteration (the compilation of the bare loop is the symmetric-copies test's), the same poses
    and scores, 15 degrees off brought under 5."""
    tless = meshes[0]
    T_gt, args = scene
    loop = LoopSettings(antialias=1, iterations=1)
    config = dataclasses.replace(get_refiner_config("tiny"), crop_size=CROP, output_size=MAP)
    refiner = SceneRefiner(ORACLE, config, SETTINGS, [RefineObject(18, tless, np.eye(4)[None])],
                           loop=loop)
    (got,) = refiner([args["images"][0]], K_FULL[None], None, [18], [args["hypotheses"][0]])
    one = {k: (v if k in ("images", "Ks", "T_cam_world") else np.asarray(v)[:1])
           for k, v in args.items()}
    # Two symmetry slots, the second masked: the shapes of the symmetric-copies test.
    one.update(symmetries=np.tile(np.eye(4), (1, 2, 1, 1)), symmetry_mask=np.array([[True, False]]))
    bare = _run(meshes, one, loop=loop)
    _same_poses(got.T_world_obj, bare.poses[0])
    np.testing.assert_allclose(got.score, bare.scores[0], atol=1e-4)
    start, deg = (_errors(T, T_gt[0])[0] for T in (args["hypotheses"][0, 0], got.T_world_obj))
    assert start > 14.0 and deg < 5.0, (start, deg)
    assert refiner.traces == 1


def _same_poses(a, b):
    """Equal up to float32 sums that XLA orders differently for another batch size."""
    a, b = np.asarray(a), np.asarray(b)
    np.testing.assert_allclose(a[..., :3, :3], b[..., :3, :3], atol=2e-4)
    np.testing.assert_allclose(a[..., :3, 3], b[..., :3, 3], atol=0.02)  # mm


def test_padding_changes_nothing_and_does_not_retrace(meshes, scene, result):
    """Garbage padding (NaN, out-of-range ids) gives the poses of copy padding, no NaN anywhere,
    fixed outputs on the padding rows; 3 instances in the same 4-bin reuse the compilation."""
    _, args = scene
    assert pad_to_bin(2) == 2 and pad_to_bin(3) == 4
    traces = len(TRACES)
    padded = _pad(_in_three_views(args), garbage=True)
    out = _run(meshes, padded)
    assert len(TRACES) == traces, "other padding contents recompiled"
    for field in out:
        assert not np.isnan(np.asarray(field)).any()
    _same_poses(out.poses[:2], result.poses[:2])
    np.testing.assert_allclose(out.scores[:2], result.scores[:2], atol=1e-4)
    np.testing.assert_array_equal(out.poses[2:], np.tile(np.eye(4), (2, 1, 1)))
    assert np.all(np.isneginf(out.scores[2:]))
    three = dict(padded, instance_mask=np.array([True, True, True, False]))
    three["hypotheses"] = padded["hypotheses"].copy()
    three["hypotheses"][2] = args["hypotheses"][1]
    three["mesh_index"] = np.array([0, 0, 0, 0], np.int32)
    three["symmetries"][2], three["symmetry_mask"][2] = np.eye(4), True
    three["view_mask"][2] = np.arange(3) == 0
    out3 = _run(meshes, three)
    assert len(TRACES) == traces, "a scene with 3 instances in the 4-bin recompiled"
    _same_poses(out3.poses[2], result.poses[1])


def test_symmetric_copies_are_duplicates(meshes):
    """A 2-fold symmetric box with S2-invariant colours: hypotheses h and h S2 refine to
    symmetric copies with equal scores. With S2 declared only one survives the first halving
    (4 -> 2); with the identity alone both do (the check this test would fail without)."""
    box = meshes[1]
    T_gt = _pose(Rotation.random(random_state=5).as_matrix(), [0.0, 0.0, 250.0], box)
    image = _image([T_gt], [box], np.eye(4))
    h0 = _pose(T_gt[:3, :3] @ _rot(8, 30), T_gt[:3, :3] @ box.center + T_gt[:3, 3] + 3.0, box)
    far = [_pose(T_gt[:3, :3] @ _rot(d, 31 + i), T_gt[:3, 3], box) for i, d in enumerate((70, 110))]
    args = dict(mesh_index=np.ones(1, np.int32), images=image[None], Ks=K_FULL[None],
                T_cam_world=np.eye(4, dtype=np.float32)[None],
                hypotheses=np.stack([h0, h0 @ S2] + far)[None],
                symmetries=np.stack([np.eye(4), S2])[None], view_mask=np.ones((1, 1), bool),
                instance_mask=np.ones(1, bool))
    survivors = {}
    for declared in (True, False):
        out = _run(meshes, dict(args, symmetry_mask=np.array([[True, declared]])),
                   loop=LoopSettings(antialias=1, iterations=1))
        # The pool: the two refined survivors and the start (h0, unrefined).
        pool = np.asarray(out.hypotheses[0], np.float64)
        a, b = pool[~np.all(np.isclose(pool, h0, atol=1e-4), axis=(1, 2))]
        survivors[declared] = _errors(a, b, (np.eye(4), S2))
    assert survivors[False][0] < 2.0 and survivors[False][1] < 2.0, survivors
    assert survivors[True][0] > 20.0, survivors


def test_three_views_converge(meshes):
    """One instance seen by 3 look_at cameras (one image each), K = 4: within 1 mm, 0.2 deg."""
    tless = meshes[0]
    eyes = np.array([[500, 0, 150], [-250, 430, 100], [-250, -430, -100]], np.float64)
    T_cw = np.stack([np.asarray(look_at(e, np.zeros(3)), np.float64) for e in eyes])
    T_gt = _pose(Rotation.random(random_state=3).as_matrix(), [5.0, -3.0, 2.0], tless)
    images = np.stack([_image([T_gt], [tless], T) for T in T_cw])
    args = dict(mesh_index=np.zeros(1, np.int32), images=images, Ks=np.tile(K_FULL, (3, 1, 1)),
                T_cam_world=T_cw.astype(np.float32), hypotheses=_hypotheses(T_gt, tless, 40)[None],
                symmetries=np.eye(4)[None, None], symmetry_mask=np.ones((1, 1), bool),
                instance_mask=np.ones(1, bool), view_mask=np.ones((1, 3), bool))
    traces = len(TRACES)
    out = _run(meshes, _pad(args, garbage=False))  # the 4-bin of the other scenes
    deg, mm = _errors(np.asarray(out.poses[0], np.float64), T_gt)
    assert deg < 0.2 and mm < 1.0, (deg, mm)
    assert out.mask_logits.shape == (4, 3, MAP, MAP) and out.boxes.shape == (4, 3, 4)
    # Views 1 and 2 now show the object 20 mm off: left out by view_mask, view 0 alone still
    # finds the truth; kept in, they pull the pose away (same compilation).
    T_off = T_gt.copy()
    T_off[:3, 3] += [20.0, 0.0, 0.0]
    wrong = np.stack([images[0]] + [_image([T_off], [tless], T) for T in T_cw[1:]])
    errs = {}
    for views in ([True, False, False], [True, True, True]):
        out = _run(meshes, _pad(dict(args, images=wrong, view_mask=np.array([views])),
                                garbage=False))
        errs[sum(views)] = _errors(np.asarray(out.poses[0], np.float64), T_gt)
    assert errs[1][1] < 2.0 and errs[3][1] > 5.0, errs
    assert len(TRACES) - traces <= 1  # the program of the scenes above (0 after them)


def test_paste_masks_against_brute_force():
    """Every map cell paints the image pixels whose centres fall in its share of the box."""
    rng = np.random.default_rng(0)
    logits = rng.normal(size=(3, 5, 7))
    boxes = np.array([[-3.3, 2.7, 14.1, 19.9], [10.2, -4.6, 33.7, 12.3], [1.1, 1.9, 6.4, 3.05]])
    H, W = 17, 29
    want = np.zeros((3, H, W), bool)
    for v, (x0, y0, x1, y1) in enumerate(boxes):
        h, w = logits.shape[1:]
        for i in range(h):
            for j in range(w):
                for r in range(H):
                    for c in range(W):
                        inside_x = x0 + j * (x1 - x0) / w <= c + 0.5 < x0 + (j + 1) * (x1 - x0) / w
                        inside_y = y0 + i * (y1 - y0) / h <= r + 0.5 < y0 + (i + 1) * (y1 - y0) / h
                        if inside_x and inside_y:
                            want[v, r, c] = logits[v, i, j] > 0
    np.testing.assert_array_equal(paste_masks(logits, boxes, (H, W)), want)


def test_antialiased_crop_is_a_block_mean():
    """A box of 4 x 16 pixels on pixel edges, antialias 4: the crop is the 4 x 4 block mean."""
    image = np.random.default_rng(1).integers(0, 256, (1, 70, 90, 3), dtype=np.uint8)
    box = np.array([[8.0, 5.0, 72.0, 69.0]], np.float32)
    crops, crop_K = antialiased_crops(image, K_FULL[None], box, 16, 4)
    want = image[0, 5:69, 8:72].astype(np.float64).reshape(16, 4, 16, 4, 3).mean((1, 3)) / 255
    np.testing.assert_allclose(crops[0], want, atol=1e-5)
    # Image pixel centre (50, 30) is at edge coordinate (50.5, 30.5): crop pixel (42.5 / 4 - 0.5,
    # 25.5 / 4 - 0.5) in the pixel-centre rule.
    ray = np.linalg.solve(K_FULL.astype(np.float64), [50.0, 30.0, 1.0])
    uv = np.asarray(crop_K[0], np.float64) @ ray
    np.testing.assert_allclose(uv[:2], [(50.5 - 8) / 4 - 0.5, (30.5 - 5) / 4 - 0.5], atol=1e-5)


@pytest.mark.parametrize("bad, match", [
    (dict(keep=0.0), "keep"), (dict(iterations=0), "iterations"), (dict(antialias=2.5),
                                                                     "antialias"),
    (dict(crop_margin=0.9), "crop_margin"), (dict(duplicate_deg=-1.0), "duplicate_deg"),
])
def test_loop_settings_refuse_bad_values(bad, match):
    with pytest.raises(ValueError, match=match):
        LoopSettings(**bad)


def test_schedule_and_bins():
    assert LoopSettings().schedule(8) == (8, 4, 2, 1)
    assert LoopSettings(keep=0.75, iterations=2).schedule(5) == (5, 4, 3)
    assert [pad_to_bin(n) for n in (0, 1, 5, 64, 65, 200)] == [1, 1, 8, 64, 128, 256]
    with pytest.raises(ValueError, match="increasing"):
        pad_to_bin(3, bins=(4, 2))
