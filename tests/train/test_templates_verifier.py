"""The templates verifier's training (``train/templates_verifier.py``), its export and loading.

The learning test's candidates are made so that the outline features cannot tell right from
wrong (the same features for both) and only the crop can: a right candidate's crop shows the
rendered silhouette's shape, a wrong one's another shape at the same place."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from flax import nnx

from threept_jax.data.pretrained import VERIFIER_DIR, load_verifier, module_arrays
from threept_jax.models.verifier import CROP, CandidateVerifier
from train import templates_verifier as T


def _candidates(path, n, seed):
    """n candidates: a disc or a square rendered; the crop shows the same shape (right) or
    the other one (wrong), on noise, in random grey levels; identical features."""
    rng = np.random.default_rng(seed)
    crops = np.zeros((n, CROP, CROP, 3), np.uint8)
    renders = np.zeros((n, CROP, CROP, 3), np.uint8)
    right = rng.random(n) < 0.3
    for i in range(n):
        shape = rng.integers(2)
        shown = shape if right[i] else 1 - shape
        for img, which, value in ((renders[i], shape, 255), (crops[i], shown,
                                                                int(rng.integers(60, 250)))):
            layer = np.zeros((CROP, CROP), np.uint8)
            if which:
                cv2.circle(layer, (32, 32), 20, value, -1)
            else:
                cv2.rectangle(layer, (14, 14), (50, 50), value, -1)
            img[...] = layer[..., None]
        crops[i] = np.clip(crops[i] + rng.normal(0, 10, crops[i].shape), 0, 255)
    features = np.tile([0.5, 0.5, 0.5, 0.8, 0.2, 0.5, 4.0, 0.3], (n, 1)).astype(np.float32)
    np.savez(path, features=features, right=right, parts=np.ones(n, int), crops=crops,
             renders=renders)


def test_it_learns_what_the_outline_cannot_say_resumes_and_exports(tmp_path):
    """Four epochs on 768 candidates (batches of 32): the held-out log-loss falls below the logistic score's
    (whose features say nothing here) and below the base rate's entropy; the same call again
    resumes the finished state without a step; the export loads back into the same
    function, and a changed file is refused with the command that remakes it."""
    _candidates(tmp_path / "a.npz", 768, 0)
    _candidates(tmp_path / "b.npz", 256, 1)
    model, figures = T.train(tmp_path / "state", [tmp_path / "a.npz"], [tmp_path / "b.npz"], 4,
                             lr=3e-3, batch=32)
    p = np.mean(np.load(tmp_path / "b.npz")["right"])
    entropy = -(p * np.log(p) + (1 - p) * np.log(1 - p))
    assert figures["val_log_loss"] < 0.5 * entropy < figures["val_log_loss_logistic"]
    assert [e["epoch"] for e in figures["epochs"]] == [1, 2, 3, 4]
    again, resumed = T.train(tmp_path / "state", [tmp_path / "a.npz"], [tmp_path / "b.npz"], 4,
                             lr=3e-3, batch=32)
    assert resumed["epochs"] == figures["epochs"]
    for k, a in module_arrays(model).items():
        np.testing.assert_array_equal(module_arrays(again)[k], a)
    T.export(model, figures, tmp_path / "out", "test")
    source = json.loads((tmp_path / "out" / "SOURCE.json").read_text())
    assert source["parameters"] == sum(a.size for a in module_arrays(model).values())
    loaded = load_verifier(tmp_path / "out")
    d = np.load(tmp_path / "b.npz")
    x = d["features"][:16]
    np.testing.assert_allclose(loaded(d["crops"][:16], d["renders"][:16], x),
                               model(d["crops"][:16], d["renders"][:16], x), atol=1e-6)
    arrays = dict(np.load(tmp_path / "out" / "verifier.npz"))
    arrays["out/bias"] = arrays["out/bias"] + 1.0
    np.savez(tmp_path / "out" / "verifier.npz", **arrays)
    with pytest.raises(ValueError, match="train.templates_verifier"):
        load_verifier(tmp_path / "out")
    with pytest.raises(FileNotFoundError, match="remake it"):
        load_verifier(tmp_path / "missing")


def test_a_fresh_verifier_adds_nothing_and_the_shipped_one_loads():
    """Its output layer starts at zero (a verifier that learned nothing leaves the score as it
    was); the shipped weights load, checked, with their recorded figures; dropout changes the
    output only when given a key."""
    import jax

    rng = np.random.default_rng(0)
    crops = rng.integers(0, 255, (4, CROP, CROP, 3), np.uint8)
    renders = rng.integers(0, 255, (4, CROP, CROP, 3), np.uint8)
    x = rng.normal(size=(4, 8)).astype(np.float32)
    np.testing.assert_array_equal(CandidateVerifier(rngs=nnx.Rngs(0))(crops, renders, x), 0.0)
    shipped = load_verifier()
    source = json.loads((VERIFIER_DIR / "SOURCE.json").read_text())
    assert source["parameters"] == sum(a.size for a in module_arrays(shipped).values())
    assert source["val_log_loss"] < source["val_log_loss_logistic"]
    z = np.asarray(shipped(crops, renders, x))
    assert np.isfinite(z).all() and np.abs(z).max() > 0
    np.testing.assert_array_equal(shipped(crops, renders, x), z)
    assert np.abs(np.asarray(shipped(crops, renders, x, dropout=jax.random.key(0))) - z).max() > 0
