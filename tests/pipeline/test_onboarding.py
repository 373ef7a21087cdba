"""Onboarding renders: the bank camera derived by hand, silhouettes against cv2.projectPoints,
visible faces against the rotated face normals, both backends, chunking.

References: the camera is rebuilt here from the definition in ``threept_jax.data.banks``
(distance 4 r, focal length 0.9 (side / 2) / tan(asin(1 / 4)), principal point at the image
centre) rather than taken from the code under test; silhouettes come from OpenCV.
"""

import math

import cv2
import numpy as np
import pytest
import trimesh

from threept_jax.geometry.grids import prior_view_rotations, super_fibonacci_rotations
from threept_jax.pipeline.onboarding import object_camera, render_chunk, render_object_views
from threept_jax.render import Mesh, Renderer

HW = (48, 48)
FACE_COLORS = np.array(
    [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0, 1, 1], [1, 0, 1]], np.float32
)


def _box(extents=(40.0, 60.0, 24.0), offset=(7.0, -3.0, 5.0)):
    """An off-centre box whose 6 faces have distinct vertex colours (unwelded corners)."""
    b = trimesh.creation.box(extents=extents)
    b.apply_translation(offset)
    normals = b.face_normals
    axis = np.abs(normals).argmax(1)
    face_kind = axis * 2 + (normals[np.arange(len(normals)), axis] > 0)
    v = b.vertices[b.faces].reshape(-1, 3)
    colors = np.repeat(FACE_COLORS[face_kind], 3, 0)
    n = np.repeat(normals, 3, 0)
    mesh = Mesh(v, np.arange(len(v)).reshape(-1, 3), n, colors=colors, name="box")
    return mesh, b, face_kind


def _hand_camera(vertices, hw):
    lo, hi = vertices.min(0), vertices.max(0)
    c = (lo + hi) / 2
    r = np.linalg.norm(vertices - c, axis=1).max()
    d = 4.0 * r
    f = 0.9 * (min(hw) / 2) / math.tan(math.asin(1 / 4))
    K = np.array([[f, 0, (hw[1] - 1) / 2], [0, f, (hw[0] - 1) / 2], [0, 0, 1.0]])
    return K, c, r, d


def test_camera_matches_the_documented_definition():
    mesh, b, _ = _box()
    K, c, r, d = _hand_camera(np.asarray(b.vertices), HW)
    K2, c2, d2 = object_camera(mesh, HW)
    np.testing.assert_allclose(K2, K, rtol=1e-12)
    np.testing.assert_allclose(c2, c, atol=1e-5)
    assert d2 == pytest.approx(d, rel=1e-6)


@pytest.mark.parametrize("backend", ["jax", "mitsuba"])
def test_silhouettes_match_projected_hull(backend):
    """The box is convex: its silhouette is the convex hull of cv2.projectPoints of its corners,
    and every projected vertex stays inside the sphere's image (90 % of the side)."""
    mesh, b, _ = _box()
    K, c, r, d = _hand_camera(np.asarray(b.vertices), HW)
    R_all = np.concatenate([prior_view_rotations(), super_fibonacci_rotations(4)])
    images = render_object_views(mesh, R_all, HW, backend=backend, chunk=8, ambient=1.0)
    assert images.shape == (16, *HW, 3) and images.dtype == np.uint8
    for R, im in zip(R_all.astype(np.float64), images):
        t = np.array([0.0, 0.0, d]) - R @ c
        uv, _ = cv2.projectPoints(np.asarray(b.vertices), cv2.Rodrigues(R)[0], t, K, None)
        uv = uv.reshape(-1, 2)
        hull = cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2)
        # Rasterise the hull at the 3 x 3 samples of each pixel (supersampled renders,
        # offsets -1/3, 0, 1/3 pixel): a pixel is non-black when any of its samples is inside.
        ys, xs = np.mgrid[0 : HW[0], 0 : HW[1]]
        offsets = [(dx, dy) for dx in (-1 / 3, 0, 1 / 3) for dy in (-1 / 3, 0, 1 / 3)]
        inside = np.array(
            [any(cv2.pointPolygonTest(hull, (float(x + dx), float(y + dy)), False) >= 0
                 for dx, dy in offsets) for x, y in zip(xs.ravel(), ys.ravel())]
        ).reshape(HW)
        mask = im.any(-1)
        iou = (mask & inside).sum() / (mask | inside).sum()
        assert iou > 0.97, iou
        centre = np.array([(HW[1] - 1) / 2, (HW[0] - 1) / 2])
        assert np.linalg.norm(uv - centre, axis=1).max() <= 0.9 * HW[0] / 2 + 1e-3


def test_visible_face_colours_follow_the_rotation():
    """The ray through the image centre hits the face whose rotated outward normal points most
    toward the camera (most negative z); with ambient 1 its pixels show that face's colour."""
    mesh, b, face_kind = _box(extents=(40.0, 40.0, 40.0), offset=(0.0, 0.0, 0.0))
    R_all = super_fibonacci_rotations(40).astype(np.float64)
    images = render_object_views(mesh, R_all, HW, chunk=8, ambient=1.0)
    axes = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1.0]])
    checked = 0
    for R, im in zip(R_all, images):
        nz = (axes @ R.T)[:, 2]
        order = np.argsort(nz)
        if nz[order[1]] - nz[order[0]] < 0.2:
            continue  # an edge near the centre: ambiguous
        want = np.round(FACE_COLORS[order[0]] * 255)
        block = im[HW[0] // 2 - 1 : HW[0] // 2 + 1, HW[1] // 2 - 1 : HW[1] // 2 + 1]
        np.testing.assert_array_equal(block.reshape(-1, 3), np.tile(want, (4, 1)))
        checked += 1
    assert checked >= 10


def test_chunks_do_not_change_the_renders():
    mesh, _, _ = _box()
    R = super_fibonacci_rotations(10)
    whole = render_object_views(mesh, R, HW, chunk=8)
    tail = render_object_views(mesh, R[8:], HW, chunk=8)
    np.testing.assert_array_equal(whole[8:], tail)
    mitsuba = render_object_views(mesh, R, HW, backend="mitsuba", chunk=8)
    fg = whole.any(-1) | mitsuba.any(-1)
    assert (whole.any(-1) == mitsuba.any(-1)).mean() > 0.995
    assert np.abs(whole.astype(int) - mitsuba)[fg].mean() < 3.0


def test_bad_rotations_raise():
    mesh, _, _ = _box()
    with pytest.raises(ValueError, match=r"\[N, 3, 3\]"):
        render_object_views(mesh, np.eye(3), HW)
    with pytest.raises(ValueError, match="chunk"):
        render_object_views(mesh, np.eye(3)[None], HW, chunk=0)


def test_default_chunk_follows_the_face_bucket_and_matches_single_views():
    """On CPU a call renders CPU_FACE_VIEWS // padded faces views (hand-derived for a 5120-face
    sphere: bucket 6144, 32768 // 6144 = 5); those batched renders, the last call padded, equal
    the views rendered one per call."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=30.0)
    mesh = Mesh(sphere.vertices, sphere.faces, sphere.vertex_normals,
                colors=np.abs(sphere.vertex_normals), name="sphere")
    renderer = Renderer(mesh)
    assert renderer.mesh.num_faces_padded == 6144
    assert render_chunk(renderer) == 5
    assert render_chunk(Renderer(_box()[0])) == 64  # 256 faces: capped
    R = super_fibonacci_rotations(7)
    sph = (np.zeros(3), 30.0)
    batched = render_object_views(renderer, R, HW, sphere=sph)
    single = render_object_views(renderer, R, HW, sphere=sph, chunk=1)
    assert batched.any()
    assert np.abs(batched.astype(int) - single).max() <= 1


def test_training_bank_and_onboarding_renders_agree_per_pixel(tmp_path):
    """Issue 13 item 1.3: the bank datagen packs for training, read back through the training
    input (``AttachRenders``), and the renders the inference Onboarder embeds for the same mesh
    file are the same images: at most 1 grey level apart on every pixel (they come from one
    function at one size with one anti-aliasing rule; PNG storage is lossless)."""
    import json

    from flax import nnx

    from datagen.banks import build_banks
    from infer.onboarding import Onboarder
    from threept_jax.data import banks
    from threept_jax.data import detector_input as pl
    from threept_jax.models.configs import DetectorConfig
    from threept_jax.models.detector import Detector

    # An asymmetric part: a plate with an off-centre peg, in mm.
    plate = trimesh.creation.box((60.0, 36.0, 12.0))
    peg = trimesh.creation.cylinder(radius=6.0, height=30.0, sections=12)
    peg.apply_translation((18.0, 8.0, 15.0))
    (tmp_path / "models").mkdir()
    trimesh.util.concatenate([plate, peg]).export(tmp_path / "models" / "obj_000005.ply")
    row = {"name": "part", "diameter": 80.0, "bank": "banks/obj_000005.npz",
           "mesh": "models/obj_000005.ply"}
    (tmp_path / "objects.json").write_text(json.dumps({"5": row}))
    size, num_t = 32, 8
    assert build_banks(tmp_path, size=size, num_templates=num_t, quiet=True) == [5]
    cfg = pl.ExampleConfig(tile_size=64, max_instances=1, num_templates=num_t,
                           max_symmetries=1, render_size=size)
    ex = {"obj_id": np.int32(5), "mask": np.zeros(1, bool),
          "rotations": np.eye(3, dtype=np.float32)[None]}
    train = pl.AttachRenders(cfg, pl.BankCache(banks.load_object_table(tmp_path))).random_map(
        ex, np.random.default_rng(0))

    dcfg = DetectorConfig(variant="tiny/16", image_size=64, render_size=size)
    ob = Onboarder(Detector(dcfg, rngs=nnx.Rngs(0)), dcfg, "m@0", num_templates=num_t,
                   template_chunk=num_t)
    seen = {}

    def recording(name, fn):
        def wrapped(params, images):
            seen[name] = np.asarray(images)
            return fn(params, images)
        return wrapped

    ob._embed_priors = recording("priors", ob._embed_priors)
    ob._embed_templates = recording("templates", ob._embed_templates)
    obj = ob.onboard(5, tmp_path / "models" / "obj_000005.ply")

    assert seen["priors"].shape == train["prior_rgb"].shape == (12, size, size, 3)
    assert train["prior_rgb"].any()
    assert np.abs(seen["priors"].astype(int) - train["prior_rgb"]).max() <= 1
    # Training samples the templates in a random order: match them by rotation.
    order = [int(np.argmin(np.abs(obj.template_rotations - r).sum((1, 2))))
             for r in train["template_rotations"]]
    assert sorted(order) == list(range(num_t))
    assert np.abs(seen["templates"][order].astype(int) - train["template_rgb"]).max() <= 1
