"""Refinement in the public API with an untrained tiny refiner: plumbing, padding, no retrace.

What refinement converges to is tested with the oracle network in
tests/pipeline/test_refine_loop.py; here: ``infer.refine`` and ``run_scene`` with a refiner
return one pose per instance in the input order, the pose before refinement is the given one,
refiner masks are image-sized and disjoint across instances, instance counts in one bin share
one compilation, and bad input gets a clear error.
"""

import dataclasses

import numpy as np
import pytest
import trimesh
from flax import nnx

import infer
from infer import api
from infer.refine import SceneRefiner, refine_objects
from tests.fixtures.poses import pose_z
from tests.fixtures.run_dirs import plumbing_scene_refiner
from threept_jax.models.configs import get_refiner_config
from threept_jax.models.refiner import Refiner
from threept_jax.pipeline.refinement import RefineSettings
from threept_jax.render import Mesh

K = np.array([[120.0, 0, 63.5], [0, 120.0, 47.5], [0, 0, 1]])


def _box_mesh(extents, name):
    tm = trimesh.creation.box(extents)
    return Mesh(np.asarray(tm.vertices, np.float32), np.asarray(tm.faces, np.int32), name=name)


@pytest.fixture(scope="module")
def refiner_models(tmp_path_factory):
    """(refiner-only Models, meshes, Models with an untrained detector and the same refiner).
    Every test refines 3 or 4 instances in one 96 x 128 view: one bin, one compiled loop, the
    plumbing tests' short loop (``plumbing_scene_refiner``)."""
    from infer.onboarding import Onboarder
    from threept_jax.models.configs import DetectorConfig
    from threept_jax.models.detector import Detector

    cfg = get_refiner_config("tiny")
    settings = RefineSettings(num_matches=16, max_faces=256, subpixel=False)
    model = Refiner(cfg, rngs=nnx.Rngs(0))
    models = infer.Models(None, None, None, None, refiner=model, refiner_config=cfg,
                          refiner_step=0, refine_settings=settings)
    meshes = {1: _box_mesh((80, 40, 20), "plate"), 2: _box_mesh((30, 30, 90), "post")}
    dcfg = DetectorConfig(variant="tiny/16", image_size=64, render_size=32)
    det = Detector(dcfg, rngs=nnx.Rngs(0))
    onboarder = Onboarder(det, dcfg, "untrained@0", cache_dir=tmp_path_factory.mktemp("ob"),
                          num_templates=48)
    both = dataclasses.replace(models, detector=det, config=dcfg, step=0, onboarder=onboarder)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(api, "SceneRefiner", plumbing_scene_refiner())
        yield models, meshes, both


def test_refine_keeps_order_and_initial_poses_and_does_not_retrace_within_a_bin(refiner_models):
    _, meshes, models = refiner_models
    image = np.random.default_rng(0).integers(0, 256, (96, 128, 3), dtype=np.uint8)
    poses = [(1, pose_z(-40, 0, 600, 10)), (2, pose_z(30, 10, 700)), (1, pose_z(10, -20, 650, 40))]
    refiner = models.scene_refiner(refine_objects(meshes))
    traces = refiner.traces  # shared by the refiners of this model in the worker
    out = infer.refine([image], [K], meshes, poses, models)
    assert [r.obj_id for r in out] == [1, 2, 1]
    for r, (_, T) in zip(out, poses):
        assert np.all(np.isfinite(r.T_world_obj)) and np.isfinite(r.score)
        np.testing.assert_allclose(r.history[0], T, atol=1e-3)
        np.testing.assert_allclose(r.T_world_obj[3], [0, 0, 0, 1])
        R = r.T_world_obj[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-4)
        assert set(r.masks) == {0} and r.masks[0].shape == (96, 128)
        assert r.masks[0].dtype == bool
    assert refiner.traces - traces <= 1  # 0 when an earlier test compiled these shapes
    traces = refiner.traces
    # Four instances fall in the same bin as three: the compiled loop is reused.
    infer.refine([image], [K], meshes, poses + [(2, pose_z(0, 0, 800))], models)
    assert refiner.traces == traces
    # Another refiner of the same structure with other weights compiles nothing and refines
    # with its own weights (arguments of the shared program, not constants baked into it).
    cfg, settings = models.refiner_config, models.refine_settings
    other = plumbing_scene_refiner()(Refiner(cfg, rngs=nnx.Rngs(1)), cfg, settings,
                                     refine_objects(meshes))
    ids, hyps = [o for o, _ in poses], [T for _, T in poses]
    mine = refiner([image], K[None], None, ids, hyps)
    theirs = other([image], K[None], None, ids, hyps)
    assert other.traces == refiner.traces == traces
    assert all(a.score != b.score for a, b in zip(mine, theirs))


def test_run_scene_refines_every_instance_with_masks_of_the_refined_poses(refiner_models):
    from infer.scene import find_instances

    _, meshes, both = refiner_models
    image = np.random.default_rng(1).integers(0, 256, (96, 128, 3), dtype=np.uint8)
    options = dict(num_scales=1, score_threshold=0.0, max_detections=4)
    got = infer.run_scene([image], [K], meshes, both, **options)
    plain = infer.run_scene([image], [K], meshes, both, refine=False, **options)
    assert 3 <= len(got) == len(plain)  # 3 or 4: the bin of the other tests
    for a, b in zip(got, plain):
        assert a.obj_id == b.obj_id and a.refine_score is not None and b.refine_score is None
        np.testing.assert_allclose(a.T_world_obj_initial, b.T_world_obj, atol=1e-4)
        assert a.masks[0].shape == (96, 128)
    # Each pixel belongs to at most one instance: the refined pose's silhouette less those of
    # the better-scored instances before it (rendered here one by one).
    total = sum(x.masks[0].astype(int) for x in got)
    assert total.max() <= 1
    renderer = both.pose_renderer(both.onboard(meshes))
    taken = np.zeros((96, 128), bool)
    for x in got:
        sil = renderer.masks(x.obj_id, x.T_world_obj[None].astype(np.float32), K, (96, 128))[0]
        np.testing.assert_array_equal(x.masks[0], sil & ~taken)
        taken |= sil
    objects = both.onboard(meshes)
    assert [x.obj_id for x in find_instances(both.scene_detector(objects, **options), [image],
                                             [K], with_masks=False)] == [x.obj_id for x in got]


def test_refine_errors_name_the_problem(refiner_models):
    models, meshes, _ = refiner_models
    image = np.zeros((96, 128, 3), np.uint8)
    with pytest.raises(KeyError, match=r"objects \[7\] are not in this refiner's object set"):
        infer.refine([image], [K], meshes, [(7, pose_z(0, 0, 500))], models)
    with pytest.raises(ValueError, match="not finite"):
        infer.refine([image], [K], meshes, [(1, np.full((4, 4), np.nan))], models)
    with pytest.raises(ValueError, match="no refiner loaded"):
        infer.refine([image], [K], meshes, [(1, pose_z(0, 0, 500))],
                     infer.Models(None, None, None, None))
    rig = [infer.Camera(K, T_cam_world=np.eye(4)), infer.Camera(K, T_cam_world=np.eye(4))]
    with pytest.raises(ValueError, match="one size"):
        infer.refine([image, np.zeros((64, 64, 3), np.uint8)], rig, meshes,
                     [(1, pose_z(0, 0, 500))], models)
    assert isinstance(models.scene_refiner(refine_objects(meshes)), SceneRefiner)


def test_track_refines_from_the_previous_pose_and_redetects_under_the_score(refiner_models):
    _, meshes, both = refiner_models
    objects = both.onboard(meshes)
    rng = np.random.default_rng(2)
    frames = [rng.integers(0, 256, (96, 128, 3), dtype=np.uint8) for _ in range(3)]
    init = [(1, pose_z(0, 0, 600)), (2, pose_z(-30, 0, 700)), (1, pose_z(30, 10, 650, 30))]
    traces = both.scene_refiner(objects).traces
    # Never re-detect: each frame starts from the previous frame's refined pose.
    got = list(infer.track(frames, [K], objects, both, init, min_score=-np.inf))
    assert [f.redetected for f in got] == [False, False, False]
    for prev, f in zip(got, got[1:]):
        for a, b in zip(prev.poses, f.poses):
            np.testing.assert_allclose(b.history[0], a.T_world_obj, atol=1e-3)
    assert all(f.latency_s > 0 for f in got)
    # A threshold no score reaches: every frame re-detects.
    options = dict(num_scales=1, score_threshold=0.0, max_detections=4)
    again = list(infer.track(frames[:2], [K], objects, both, init, min_score=np.inf, **options))
    assert [f.redetected for f in again] == [True, True]
    assert all(3 <= len(f.poses) <= 4 for f in again)
    # One compiled loop served every call (one bin, one view, one image size), and the other
    # tests' refiner of the same model shares it: at most one trace here.
    assert both.scene_refiner(objects).traces - traces <= 1
