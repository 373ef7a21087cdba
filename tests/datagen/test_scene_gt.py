"""Ground truth of generated scenes, checked against independent references.

* Visible masks (Mitsuba's instance-id AOV of the path-traced scene) against a re-render of
  every GT instance alone with the JAX rasterizer, compared with the scene's written depth map:
  a pixel of instance k is visible where its own depth equals the scene's nearest surface.
* Amodal boxes (``bbox_obj``, from per-instance ray casts on a canvas beyond the image border)
  against ``cv2.projectPoints`` of every model vertex.
* ``visib_fract`` and pixel counts against the mask PNGs; masks nested and disjoint.
* Multi-view rigs: every view's ``T_cam_world`` and ``T_cam_obj`` give one world pose per object.
* ``models_info.json`` diameters against brute-force pairwise distances of the PLY vertices.

Scenes: procedural parts only, 128 x 96, 4 spp.
"""

import json

import cv2
import numpy as np
import pytest
from scipy.spatial.distance import pdist

from datagen import generate
from threept_jax.data.bop import BopDataset
from threept_jax.data.ply import load_ply_vertices
from threept_jax.render import load_mesh, raster, to_raster_mesh

W, H = 128, 96
COMMON = ["--meshes", "procedural:8", "--procedural-max-faces", "1500", "--resolution", str(W),
          str(H), "--spp", "4", "--image-format", "png", "--quiet", "--seed", "5"]


@pytest.fixture(scope="module")
def single(tmp_path_factory):
    """2 scenes x 2 single views, every view a close-up (objects cut by the image border)."""
    out = tmp_path_factory.mktemp("single")
    generate.main(COMMON + ["--out", str(out), "--num-scenes", "2", "--images-per-scene", "2",
                            "--instances", "10", "--closeup-probability", "1.0"])
    return out


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """One scene seen by a ring of 3 calibrated cameras."""
    out = tmp_path_factory.mktemp("rig")
    generate.main(COMMON + ["--out", str(out), "--num-scenes", "1", "--views", "3",
                            "--instances", "8", "--layout", "drop"])
    return out


def _images(root):
    split = BopDataset(root).split("train_pbr")
    for sid in split.scene_ids:
        scene = split.scene(sid)
        for im_id in scene.image_ids:
            yield scene, im_id


_RASTER = {}


def _raster_mesh(root, obj_id):
    key = (str(root), obj_id)
    if key not in _RASTER:
        mesh = load_mesh(root / "models" / f"obj_{obj_id:06d}.ply", models_info=None)
        # One face bucket for all parts: one compiled renderer for the whole test.
        _RASTER[key] = to_raster_mesh(mesh, face_bucket=2048)
    return _RASTER[key]


@pytest.mark.parametrize("which", ["single", "rig"])
def test_visible_masks_match_a_jax_rerender(which, request):
    root = request.getfixturevalue(which)
    checked = 0
    for scene, im_id in _images(root):
        cam = scene.cameras[im_id]
        depth = scene.depth(im_id).astype(np.float64)
        for k, (gt, info) in enumerate(zip(scene.gt[im_id], scene.gt_info[im_id])):
            out = raster.render(_raster_mesh(root, gt.obj_id), gt.T_cam_obj[None],
                                cam.K, (H, W), ("depth",))
            d = np.asarray(out["depth"][0], np.float64)
            # The written depth is quantised to 0.1 mm; the backends agree to ~0.2 mm.
            mine = (d > 0) & (np.abs(d - depth) <= 0.5 + 2e-3 * d)
            visib = scene.mask_visib(im_id, k)
            union = (mine | visib).sum()
            if info.visib_fract > 0.5:
                assert union > 0
                iou = (mine & visib).sum() / union
                assert iou >= 0.98, (scene.scene_id, im_id, k, iou)
                checked += 1
            elif union:
                # Partly hidden instances: still the same pixels up to contact lines.
                assert (mine & visib).sum() / union >= 0.8
    assert checked >= 5


def _projected_extent(root, gt, K):
    v = load_ply_vertices(root / "models" / f"obj_{gt.obj_id:06d}.ply")
    X = v @ gt.T_cam_obj[:3, :3].T + gt.T_cam_obj[:3, 3]
    if (X[:, 2] <= 1.0).any():
        return None
    uv, _ = cv2.projectPoints(v, cv2.Rodrigues(gt.T_cam_obj[:3, :3])[0], gt.T_cam_obj[:3, 3],
                              K, None)
    uv = uv.reshape(-1, 2)
    return uv.min(0), uv.max(0)


@pytest.mark.parametrize("which", ["single", "rig"])
def test_amodal_boxes_hold_the_projected_model(which, request):
    """bbox_obj [x, y, w, h] spans the pixel centres x..x+w of the full silhouette, so the
    projected vertices reach at least as far (up to float rounding) and less than 1.5 px more
    (a pixel centre lies within half a pixel of the silhouette's extreme point, plus edges
    passing between pixel centres)."""
    root = request.getfixturevalue(which)
    truncated = checked = 0
    for scene, im_id in _images(root):
        K = scene.cameras[im_id].K
        for gt, info in zip(scene.gt[im_id], scene.gt_info[im_id]):
            if info.px_count_visib == 0:
                assert list(info.bbox_obj) == [-1, -1, -1, -1]
                continue
            ext = _projected_extent(root, gt, K)
            if ext is None:
                continue
            (u0, v0), (u1, v1) = ext
            x, y, w, h = info.bbox_obj
            assert u0 <= x + 1e-3 and v0 <= y + 1e-3, (ext, info.bbox_obj)
            assert u1 >= x + w - 1e-3 and v1 >= y + h - 1e-3, (ext, info.bbox_obj)
            assert u0 > x - 1.5 and v0 > y - 1.5 and u1 < x + w + 1.5 and v1 < y + h + 1.5
            truncated += x < 0 or y < 0 or x + w >= W or y + h >= H
            checked += 1
    assert checked >= 10
    if which == "single":
        assert truncated >= 3  # close-ups: the canvas beyond the border is exercised


@pytest.mark.parametrize("which", ["single", "rig"])
def test_counts_and_masks_are_consistent(which, request):
    root = request.getfixturevalue(which)
    for scene, im_id in _images(root):
        visib_all = []
        for k, info in enumerate(scene.gt_info[im_id]):
            full = scene.mask(im_id, k)
            visib = scene.mask_visib(im_id, k)
            assert not (visib & ~full).any()
            assert info.px_count_visib == visib.sum()
            ys, xs = np.nonzero(full)
            x, y, w, h = info.bbox_obj
            inside = x >= 0 and y >= 0 and x + w < W and y + h < H
            if info.px_count_visib and inside:
                assert info.px_count_all == full.sum()
                assert [x, y, w, h] == [xs.min(), ys.min(), xs.max() - xs.min(),
                                        ys.max() - ys.min()]
            else:
                assert info.px_count_all >= full.sum()
            if info.px_count_all:
                assert info.visib_fract == pytest.approx(visib.sum() / info.px_count_all)
            visib_all.append(visib)
        if visib_all:
            assert np.stack(visib_all).sum(0).max() <= 1  # visible masks never overlap


def test_rig_views_agree_on_world_poses(rig):
    split = BopDataset(rig).split("train_pbr")
    scene = split.scene(split.scene_ids[0])
    assert scene.image_ids == [0, 1, 2]
    world = []
    for im_id in scene.image_ids:
        cam = scene.cameras[im_id]
        assert cam.T_cam_world is not None and cam.depth_scale == pytest.approx(0.1)
        world.append([np.linalg.inv(cam.T_cam_world) @ g.T_cam_obj for g in scene.gt[im_id]])
    world = np.array(world)
    assert world.shape[1] >= 4
    np.testing.assert_allclose(world[1], world[0], atol=1e-6 * 1000)
    np.testing.assert_allclose(world[2], world[0], atol=1e-6 * 1000)
    centres = [-(c.T_cam_world[:3, :3].T @ c.T_cam_world[:3, 3]) for c in scene.cameras.values()]
    assert min(np.linalg.norm(a - b) for a in centres for b in centres if a is not b) > 50.0


def test_models_info_and_reader(single):
    ds = BopDataset(single)
    models = ds.models()
    manifest = json.loads((single / "train_pbr" / "manifest.json").read_text())
    used = {g.obj_id for scene, im in _images(single) for g in scene.gt[im]}
    assert used <= set(models) and {int(k) for k in manifest["objects"]} == used
    pool = generate.build_pool(["procedural:8"], 5, procedural_max_faces=1500)
    for oid, m in models.items():
        v = load_ply_vertices(m.path)
        assert m.diameter == pytest.approx(pdist(v).max(), rel=1e-9)
        rec = pool.records[oid - 1]
        assert len(m.symmetries.discrete) == len(rec.symmetries.discrete)
        np.testing.assert_allclose(m.symmetries.discrete.reshape(-1, 16),
                                   np.reshape(rec.symmetries.discrete, (-1, 16)), atol=1e-9)
        assert len(m.symmetries.continuous) == len(rec.symmetries.continuous)
    scene = ds.split("train_pbr").scene(0)
    rgb = scene.image(0)
    assert rgb.shape == (H, W, 3) and rgb.dtype == np.uint8 and 10 < rgb.mean() < 245
