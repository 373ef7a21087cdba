"""Inference onboarding: the default bank's coverage against a brute-force float64 reference,
block-wise embedding against one-shot embedding of the bank renders, and progress that counts
exactly the views done, object by object."""

import numpy as np
import pytest
import trimesh
from flax import nnx
from scipy.spatial.transform import Rotation

import infer.onboarding as onboarding
from infer.onboarding import ONBOARD_TEMPLATES, Onboarder
from threept_jax.data.banks import BANK_TEMPLATES
from threept_jax.geometry.grids import super_fibonacci_rotations
from threept_jax.models.configs import DetectorConfig
from threept_jax.models.detector import Detector
from threept_jax.pipeline.onboarding import render_bank
from threept_jax.render import Mesh

#: Object generation keeps the top-K templates at least this far apart (docs/design.md section 1.2).
HYPOTHESIS_SEPARATION_DEG = 45.0


def _covering_radius_deg(n: int, queries: np.ndarray) -> float:
    """Largest angle from a query rotation to its nearest grid rotation: brute force over all
    pairs in float64, |q . g| = cos(angle / 2) for unit quaternions (q ~ -q)."""
    g = Rotation.from_matrix(super_fibonacci_rotations(n).astype(np.float64)).as_quat()
    best = np.concatenate([np.abs(queries[s : s + 10_000] @ g.T).max(1)
                           for s in range(0, len(queries), 10_000)])
    return float(np.degrees(2 * np.arccos(np.clip(best.min(), -1.0, 1.0))))


def test_default_bank_covers_half_the_hypothesis_separation():
    """The default is the smallest grid of the ladder (768, 1024) whose covering radius is
    under half of 45 degrees, and well under the paper's 5140 renders."""
    queries = Rotation.random(50_000, random_state=0).as_quat()
    half = HYPOTHESIS_SEPARATION_DEG / 2
    assert _covering_radius_deg(ONBOARD_TEMPLATES, queries) < half
    assert _covering_radius_deg(768, queries) > half
    assert ONBOARD_TEMPLATES <= BANK_TEMPLATES // 5
    cfg = DetectorConfig(variant="tiny/16", image_size=64, render_size=32)
    ob = Onboarder(Detector(cfg, rngs=nnx.Rngs(0)), cfg, "m@0")
    assert (ob.num_templates, ob.template_chunk) == (1024, 64)  # CPU blocks (module constants)


def _box(extents, name):
    tm = trimesh.creation.box(extents)
    return Mesh(np.asarray(tm.vertices, np.float32), np.asarray(tm.faces, np.int32), name=name)


@pytest.fixture(scope="module")
def tiny():
    cfg = DetectorConfig(variant="tiny/16", image_size=64, render_size=32)
    return Detector(cfg, rngs=nnx.Rngs(0)), cfg


def test_blocks_embed_like_the_whole_bank(tiny):
    """Rendering and embedding in padded blocks of 16 gives what the detector returns for the
    whole bank (render_bank's images at the model's render size, embedded in one call)."""
    model, cfg = tiny
    mesh = _box((80, 40, 20), "plate")
    ob = Onboarder(model, cfg, "m@0", num_templates=40, template_chunk=16)
    obj = ob.onboard(3, mesh)
    rb = render_bank(mesh, 3, float(mesh.diameter), mesh.symmetries, 32, 40)
    prior = model.embed_object(rb.prior_rgb[None])[0]
    bank = model.embed_templates(rb.template_rgb[None])[0]
    np.testing.assert_allclose(obj.prior_tokens, np.asarray(prior), atol=1e-4)
    np.testing.assert_allclose(obj.template_bank, np.asarray(bank), atol=1e-4)
    np.testing.assert_allclose(obj.template_rotations, rb.template_rotations)
    np.testing.assert_allclose(obj.center, rb.center)
    assert set(ob.timings[3]) == {"render", "embed"}


class _RecordingBar:
    """Stands in for tqdm: records updates under the postfix current at the time."""

    instances = []

    def __init__(self, total, **kwargs):
        self.total, self.kwargs, self.postfix, self.events = total, kwargs, None, []
        _RecordingBar.instances.append(self)

    def set_postfix_str(self, s):
        self.postfix = s

    def update(self, n):
        self.events.append((self.postfix, n))

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_progress_counts_views_done_per_object(tiny, tmp_path, monkeypatch):
    """The bar's total equals the views reported (12 priors + T templates per object, a cached
    object at once); each object's views come under its own postfix, in blocks."""
    model, cfg = tiny
    monkeypatch.setattr(onboarding, "tqdm", _RecordingBar)
    meshes = {1: _box((80, 40, 20), "plate"), 2: _box((30, 30, 90), "post")}
    ob = Onboarder(model, cfg, "m@0", cache_dir=tmp_path, num_templates=20,
                   template_chunk=8)
    ob.onboard(1, meshes[1])  # object 1 is cached before the run
    ob.onboard_all(meshes)
    bar = _RecordingBar.instances[-1]
    assert bar.kwargs["unit"] == "view"
    assert bar.total == 2 * (12 + 20) == sum(n for _, n in bar.events)
    by_object = {}
    for postfix, n in bar.events:
        by_object.setdefault(postfix, []).append(n)
    assert by_object == {"object 1/2: 1 (plate)": [32], "object 2/2: 2 (post)": [12, 8, 8, 4]}
