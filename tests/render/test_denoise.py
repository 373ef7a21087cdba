"""Open Image Denoise on path-traced renders: closer to the converged image, deterministic
whatever the thread count, bad input refused."""

import subprocess
import sys

import numpy as np
import pytest
import trimesh

from threept_jax.render import Mesh
from threept_jax.render.denoise import denoise
from threept_jax.render.mitsuba_backend import Material, MitsubaScene, load_mitsuba

HW = (60, 80)


def _scene() -> tuple[MitsubaScene, np.ndarray, np.ndarray]:
    """A textured-looking box (vertex colours) on a grey ground under an area light."""
    box = trimesh.creation.box(extents=(60, 40, 30))
    box = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, 8.0)
    v = np.asarray(box[0])
    colors = 0.5 + 0.4 * np.sign(np.sin(v[:, :1] / 6.0)) * np.array([[1.0, 0.2, -0.6]])
    mesh = Mesh(vertices=v, faces=np.asarray(box[1]), colors=colors.clip(0, 1))
    scene = MitsubaScene(max_depth=4)
    T = np.eye(4)
    T[2, 3] = 15.0
    scene.add_object(mesh, T, Material("diffuse"))
    scene.set_ground(size=500.0)
    scene.set_environment((0.2, 0.2, 0.25))
    light = np.eye(4)
    light[:3, :3] = np.diag([1.0, -1.0, -1.0])  # emitting toward -z, down onto the box
    light[:3, 3] = (40.0, -30.0, 200.0)
    scene.add_area_light(light, (80, 80), (8, 8, 8))
    K = np.array([[70.0, 0, 39.5], [0, 70.0, 29.5], [0, 0, 1]])
    T_cw = np.diag([1.0, -1.0, -1.0, 1.0])  # looking down -z from z = 160
    T_cw[2, 3] = 160.0
    return scene, K, T_cw


def test_denoised_render_is_closer_to_the_converged_one():
    """4 samples per pixel + OIDN (fed the albedo and normal) against 4 raw samples, both
    scored against 512 samples of the same view (the reference: Mitsuba converged)."""
    load_mitsuba()
    scene, K, T = _scene()
    ref = scene.render(K, T, HW, spp=512, seed=1, outputs=("rgb",), linear=True)["rgb"]
    raw = scene.render(K, T, HW, spp=4, seed=2, outputs=("rgb",), linear=True)["rgb"]
    den = scene.render(K, T, HW, spp=4, seed=2, outputs=("rgb",), linear=True,
                       denoise=True)["rgb"]
    assert den.shape == HW + (3,) and den.dtype == np.float32 and (den >= 0).all()

    def rmse(x):
        return float(np.sqrt(np.mean((x - ref) ** 2)))

    assert rmse(den) < 0.4 * rmse(raw), (rmse(den), rmse(raw))
    # The image is not blurred away: its mean brightness is kept within 3 %.
    assert abs(den.mean() / ref.mean() - 1) < 0.03


_DETERMINISM = """
import hashlib, numpy as np
from threept_jax.render.denoise import denoise
rng = np.random.default_rng(0)
base = 0.3 + 0.2 * np.sin(np.arange(96) / 7.0)[None, :, None] * np.ones((64, 96, 3))
color = (base * rng.gamma(2.0, 0.5, base.shape)).astype(np.float32)
normal = np.zeros_like(color); normal[..., 2] = 1
print(hashlib.sha256(denoise(color, base.clip(0, 1), normal).tobytes()).hexdigest())
"""


def test_denoise_does_not_depend_on_the_thread_count():
    """Datagen's images are a function of the seed: OIDN pinned to one core gives the same
    bytes as OIDN on all of them."""
    digests = []
    for prefix in (["taskset", "-c", "0"], []):
        out = subprocess.run([*prefix, sys.executable, "-c", _DETERMINISM], check=True,
                             capture_output=True, text=True).stdout.split()
        digests.append(out[-1])
    assert digests[0] == digests[1]


def test_bad_input_is_refused():
    c = np.ones((8, 8, 3), np.float32)
    with pytest.raises(ValueError, match="color must be"):
        denoise(c[..., 0], c, c)
    with pytest.raises(ValueError, match="albedo must have"):
        denoise(c, c[:4], c)
    bad = c.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        denoise(bad, c, c)
