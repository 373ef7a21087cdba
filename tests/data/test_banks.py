"""Render banks: file round trip, lazy reading, the render camera, ray rotations, object table."""

import json
import os

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from threept_jax.data import banks
from threept_jax.geometry import camera
from threept_jax.geometry.grids import prior_view_rotations, super_fibonacci_rotations
from threept_jax.geometry.symmetry import ContinuousSymmetry, Symmetries


def _bank(rng, obj_id=3, num_templates=10, size=24, symmetries=None):
    return banks.RenderBank(
        obj_id=obj_id,
        prior_rgb=rng.integers(0, 256, (12, size, size, 3), dtype=np.uint8),
        prior_rotations=prior_view_rotations(),
        template_rgb=rng.integers(0, 256, (num_templates, size, size, 3), dtype=np.uint8),
        template_rotations=super_fibonacci_rotations(num_templates),
        symmetries=banks.bank_symmetries(symmetries or Symmetries()),
        diameter=123.0, center=[1.0, -2.0, 3.0], radius=70.0)


def test_save_load_roundtrip_and_lazy_subset(tmp_path):
    rng = np.random.default_rng(0)
    bank = _bank(rng)
    path = tmp_path / "banks" / "obj_000003.npz"
    banks.save_bank(path, bank)
    assert sorted(os.listdir(path.parent)) == ["obj_000003.npz"]  # no temporary left behind
    got = banks.load_bank(path)
    for name in ("prior_rgb", "prior_rotations", "template_rgb", "template_rotations",
                 "symmetries", "center"):
        np.testing.assert_array_equal(getattr(got, name), getattr(bank, name), err_msg=name)
    assert (got.obj_id, got.diameter, got.radius) == (3, 123.0, 70.0)
    assert not got.template_rgb.flags.writeable
    # The npz is a plain zip of .npy members readable by NumPy (no pickle).
    with np.load(path, allow_pickle=False) as z:
        assert int(z["version"]) == banks.BANK_FORMAT_VERSION
    lazy = banks.BankFile(path)
    idx = np.array([7, 0, 7, 4])
    np.testing.assert_array_equal(lazy.templates(idx), bank.template_rgb[idx])
    np.testing.assert_array_equal(lazy.priors(), bank.prior_rgb)
    with pytest.raises(IndexError, match="out of range"):
        lazy.templates([10])
    # Pickled handles reopen their memory map in the new process.
    import pickle

    again = pickle.loads(pickle.dumps(lazy))
    np.testing.assert_array_equal(again.templates([2]), bank.template_rgb[[2]])


def test_jpeg_banks_are_close(tmp_path):
    rng = np.random.default_rng(1)
    bank = _bank(rng)
    smooth = np.stack([cv2.GaussianBlur(im, (0, 0), 3) for im in bank.template_rgb])
    bank = banks.RenderBank(**{**bank.__dict__, "template_rgb": smooth})
    banks.save_bank(tmp_path / "b.npz", bank, image_format="jpg")
    got = banks.load_bank(tmp_path / "b.npz")
    assert np.abs(got.template_rgb.astype(int) - smooth).mean() < 2.0


def test_failed_write_keeps_the_old_file(tmp_path, monkeypatch):
    rng = np.random.default_rng(2)
    path = tmp_path / "b.npz"
    banks.save_bank(path, _bank(rng, obj_id=1))

    def broken_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError, match="disk full"):
        banks.save_bank(path, _bank(rng, obj_id=2))
    monkeypatch.undo()
    assert banks.BankFile(path).obj_id == 1
    assert os.listdir(tmp_path) == ["b.npz"]


def test_render_camera_sphere_fills_the_stated_share():
    """Brute force: project dense points of the bounding sphere with OpenCV and measure."""
    h, w, radius = 60, 80, 45.0
    K, distance = banks.render_camera((h, w), radius)
    centre = np.array([5.0, -7.0, 12.0])
    R = Rotation.random(random_state=3).as_matrix()
    T = banks.render_pose(R, centre, distance)
    rng = np.random.default_rng(4)
    dirs = rng.normal(size=(200_000, 3))
    pts = centre + radius * dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    uv, _ = cv2.projectPoints(pts, rvec, T[:3, 3], K, None)
    uv = uv[:, 0]
    # Pixel-centre coordinates: the image spans [-0.5, w - 0.5]; the disc is centred.
    span_u = uv[:, 0].max() - uv[:, 0].min()
    span_v = uv[:, 1].max() - uv[:, 1].min()
    assert span_u == pytest.approx(banks.FILL * min(h, w), rel=2e-3)
    assert span_v == pytest.approx(banks.FILL * min(h, w), rel=2e-3)
    c_uv, _ = cv2.projectPoints(centre[None], rvec, T[:3, 3], K, None)
    np.testing.assert_allclose(c_uv[0, 0], [(w - 1) / 2, (h - 1) / 2], atol=1e-9)
    assert np.linalg.norm(T[:3, :3] @ centre + T[:3, 3]) == pytest.approx(
        banks.DISTANCE_FACTOR * radius)


def test_ray_rotation_is_the_shortest_arc():
    rng = np.random.default_rng(5)
    pts = rng.normal(size=(50, 3)) * [300, 200, 50] + [0, 0, 600]
    R = camera.ray_rotation(pts)
    for p, r in zip(pts, R, strict=True):
        d = p / np.linalg.norm(p)
        ref, _ = Rotation.align_vectors([d], [[0.0, 0.0, 1.0]])
        np.testing.assert_allclose(r, ref.as_matrix(), atol=1e-9)
    np.testing.assert_allclose(camera.ray_rotation(np.array([0.0, 0, 5])), np.eye(3), atol=1e-12)


def test_object_centred_rotation_puts_the_centre_on_the_axis():
    rng = np.random.default_rng(6)
    R = Rotation.random(20, random_state=7).as_matrix()
    t = rng.normal(size=(20, 3)) * [200, 150, 30] + [0, 0, 700]
    c = np.array([10.0, -4.0, 25.0])
    centre_cam = np.einsum("nij,j->ni", R, c) + t
    R_obj = camera.object_centred_rotation(R, centre_cam)
    # In the virtual camera R_ray^T, the object centre lies on +z.
    virt = np.einsum("nji,nj->ni", camera.ray_rotation(centre_cam), centre_cam)
    np.testing.assert_allclose(virt[:, :2], 0.0, atol=1e-9)
    assert np.all(virt[:, 2] > 0)
    # R_ray^T maps the camera frame to the virtual one, so R_obj = R_ray^T R (independently
    # rebuilt from SciPy's shortest-arc rotation) and camera_rotation inverts it.
    for i in range(20):
        ray, _ = Rotation.align_vectors([centre_cam[i] / np.linalg.norm(centre_cam[i])],
                                        [[0.0, 0.0, 1.0]])
        np.testing.assert_allclose(R_obj[i], ray.as_matrix().T @ R[i], atol=1e-9)
    np.testing.assert_allclose(camera.camera_rotation(R_obj, centre_cam), R, atol=1e-9)


def test_bank_symmetries_follow_bop():
    cont = Symmetries(continuous=(ContinuousSymmetry(np.array([0.0, 0.0, 1.0]), np.zeros(3)),))
    sym = banks.bank_symmetries(cont)
    n = int(np.ceil(np.pi / banks.BANK_SYM_DISC_STEP))
    assert sym.shape == (n, 4, 4) and sym.dtype == np.float32
    np.testing.assert_array_equal(sym[0], np.eye(4))
    ref = Rotation.from_rotvec(np.outer(np.arange(n) * 2 * np.pi / n, [0, 0, 1])).as_matrix()
    np.testing.assert_allclose(sym[:, :3, :3], ref, atol=1e-6)
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    disc = banks.bank_symmetries(Symmetries(discrete=flip[None]))
    np.testing.assert_allclose(disc, np.stack([np.eye(4), flip]), atol=1e-7)


def test_bounding_sphere_contains_vertices():
    v = np.random.default_rng(8).uniform(-1, 1, (500, 3)) * [40, 10, 5] + [3, 4, 5]
    c, r = banks.bounding_sphere(v)
    np.testing.assert_allclose(c, (v.min(0) + v.max(0)) / 2)
    assert np.linalg.norm(v - c, axis=1).max() == pytest.approx(r)


def test_bank_validation_errors(tmp_path):
    rng = np.random.default_rng(9)
    good = _bank(rng).__dict__
    with pytest.raises(ValueError, match="rotation"):
        banks.RenderBank(**{**good, "template_rotations": np.ones((10, 3, 3))})
    with pytest.raises(ValueError, match="identity"):
        banks.RenderBank(**{**good, "symmetries": np.zeros((1, 4, 4))})
    with pytest.raises(ValueError, match="uint8"):
        banks.RenderBank(**{**good, "prior_rgb": np.zeros((12, 24, 24, 3), np.float32)})
    with pytest.raises(FileNotFoundError, match="datagen"):
        banks.BankFile(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a render bank"):
        banks.BankFile(tmp_path / "junk.npz")


def test_object_table_roundtrip_and_errors(tmp_path):
    sym = Symmetries(discrete=np.diag([1.0, -1.0, -1.0, 1.0])[None])
    entries = [
        banks.ObjectEntry(1, "mug", 110.5, Symmetries(), tmp_path / "banks" / "obj_000001.npz",
                          "train"),
        banks.ObjectEntry(7, "bolt", 42.0, sym, tmp_path / "banks" / "obj_000007.npz", None),
    ]
    banks.write_object_table(tmp_path, entries)
    raw = json.loads((tmp_path / "objects.json").read_text())
    assert raw["1"]["bank"] == os.path.join("banks", "obj_000001.npz")
    table = banks.load_object_table(tmp_path)
    assert list(table) == [1, 7]
    assert table[1].name == "mug" and table[1].split == "train" and table[7].split is None
    assert table[1].bank_path == (tmp_path / "banks" / "obj_000001.npz").resolve()
    np.testing.assert_array_equal(table[7].symmetries.discrete, sym.discrete)
    with pytest.raises(FileNotFoundError, match="objects.json"):
        banks.load_object_table(tmp_path / "nowhere")
    (tmp_path / "objects.json").write_text(json.dumps({"3": {"diameter": 0.1, "bank": "b"}}))
    with pytest.raises(ValueError, match="metres"):
        banks.load_object_table(tmp_path)
    (tmp_path / "objects.json").write_text(json.dumps({"3": {"bank": "b"}}))
    with pytest.raises(ValueError, match="diameter"):
        banks.load_object_table(tmp_path)
