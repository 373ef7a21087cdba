"""The full-image detection core (threept_jax/pipeline/detection.py): score modes against a
float64 NumPy reference, and one forward pass serving several modes without changing any."""

import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from threept_jax.models.configs import DetectorConfig
from threept_jax.models.detector import Detector, detection_scores
from threept_jax.pipeline.detection import (
    SCORE_MODES,
    DetectionSettings,
    FullImageDetector,
    model_points,
)
from threept_jax.testing.detector import random_queries


def test_score_modes_match_a_float64_reference():
    rng = np.random.default_rng(0)
    p, d = rng.normal(0, 4, (2, 7)), rng.normal(0, 4, (2, 7))
    sig = lambda x: 1.0 / (1.0 + np.exp(-x))  # noqa: E731
    ref = {"product": sig(p) * sig(d), "presence": sig(p), "template": sig(d)}
    for mode in SCORE_MODES:
        got = detection_scores(jnp.asarray(p, jnp.float32), jnp.asarray(d, jnp.float32), mode)
        np.testing.assert_allclose(np.asarray(got), ref[mode], rtol=1e-5, err_msg=mode)
    with pytest.raises(ValueError, match="unknown detection score mode 'max'"):
        detection_scores(jnp.zeros(3), jnp.zeros(3), "max")
    with pytest.raises(ValueError, match="score_modes"):
        DetectionSettings(score_modes=("product", "best"))


def test_model_points_keep_the_extreme_vertices():
    v = np.random.default_rng(1).normal(0, 10, (5000, 3))
    pts = model_points(v, 64)
    assert pts.shape == (64, 3) and pts.dtype == np.float32
    np.testing.assert_array_equal(pts.min(0), v.min(0).astype(np.float32))
    np.testing.assert_array_equal(pts.max(0), v.max(0).astype(np.float32))


def test_several_modes_share_one_forward_without_changing_any():
    cfg = DetectorConfig(variant="tiny/16", image_size=64, render_size=32)
    model = Detector(cfg, rngs=nnx.Rngs(0))
    graphdef, params = nnx.split(model)
    rng = np.random.default_rng(0)
    queries = random_queries(cfg, 2, 12, 32, rng)
    image = rng.integers(0, 256, (64, 96, 3), dtype=np.uint8)
    K = np.array([[120.0, 0, 47.5], [0, 120, 31.5], [0, 0, 1]], np.float32)
    settings = dict(score_threshold=0.0, max_detections=6, candidates_per_object=16,
                    num_hypotheses=2)
    both = FullImageDetector(graphdef, 64, DetectionSettings(score_modes=SCORE_MODES,
                                                             **settings), num_scales=2)
    out = both(params, image, K, queries)
    assert set(out) == set(SCORE_MODES)
    for mode in SCORE_MODES:
        alone = FullImageDetector(graphdef, 64, DetectionSettings(score_modes=(mode,),
                                                                  **settings), num_scales=2)
        ref = alone(params, image, K, queries)[mode]
        assert np.asarray(out[mode]["valid"]).sum() == 6
        for k in ("boxes", "scores", "object", "poses", "template_scores"):
            np.testing.assert_allclose(np.asarray(out[mode][k]), np.asarray(ref[k]), rtol=1e-5,
                                       atol=1e-6, err_msg=f"{mode} {k}")
    # The modes rank differently: presence alone and the product do not pick the same list.
    assert not np.allclose(np.asarray(out["presence"]["scores"]),
                           np.asarray(out["product"]["scores"]))


def test_detectors_of_one_model_structure_share_their_compiled_function():
    """Two models of one config (other weights) give equal GraphDefs: their detectors share the
    jitted function of an image size; other settings, tiles or sizes get their own."""
    cfg = DetectorConfig(variant="tiny/16", image_size=64, render_size=32)
    (g0, _), (g1, _) = (nnx.split(Detector(cfg, rngs=nnx.Rngs(s))) for s in (0, 1))
    a = FullImageDetector(g0, 64, DetectionSettings(), num_scales=2)
    b = FullImageDetector(g1, 64, DetectionSettings(), num_scales=2)
    assert a.compiled((64, 96)) is b.compiled((64, 96))
    others = [FullImageDetector(g1, 64, DetectionSettings(max_detections=7), num_scales=2),
              FullImageDetector(g1, 64, DetectionSettings(), num_scales=3)]
    assert all(o.compiled((64, 96)) is not a.compiled((64, 96)) for o in others)
    assert a.compiled((64, 128)) is not a.compiled((64, 96))
    assert a.compiled((64, 96), (20.0, 40.0)) is not a.compiled((64, 96))
