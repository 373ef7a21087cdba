"""3PT-R network: shapes, unit descriptors, scores, independence of hypotheses, one encoder for
real crops and renders, jit, the paper size's parameter count and the memory plan."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from threept_jax.models.aliked import ALIKEDDescriptors
from threept_jax.models.configs import (
    REFINER_SIZES,
    RefinerConfig,
    ViTConfig,
    get_refiner_config,
)
from threept_jax.models.refiner import Refiner, _saved_residual_bytes, memory_plan
from threept_jax.models.vit import ViT, count_params

B, K, V = 1, 3, 2
CFG = get_refiner_config("tiny")  # tiny/16, 64 px crops, 32 x 32 maps, C = 32


@pytest.fixture(scope="module")
def model():
    return Refiner(CFG, rngs=nnx.Rngs(0))


@pytest.fixture(scope="module")
def inputs():
    rng = np.random.default_rng(0)
    s = CFG.crop_size
    real = rng.integers(0, 256, (B, V, s, s, 3), dtype=np.uint8)
    renders = rng.uniform(size=(B, K, V, s, s, 3)).astype(np.float32)
    return real, renders


TRACES = []


@nnx.jit
def forward(model, real, renders):
    TRACES.append(1)  # Python side effect: runs once per trace
    return model(real, renders)


def test_output_shapes_dtypes_and_unit_descriptors(model, inputs):
    out = forward(model, *inputs)
    h, c = CFG.output_size, CFG.descriptor_dim
    assert h == 32 and c == 32
    expected = {"real_desc": (B, K, V, h, h, c), "render_desc": (B, K, V, h, h, c),
                "mask_logits": (B, K, V, h, h), "view_scores": (B, K, V), "scores": (B, K)}
    assert {k: v.shape for k, v in out.items()} == expected
    assert all(v.dtype == jnp.float32 for v in out.values())
    for key in ("real_desc", "render_desc"):
        norms = np.linalg.norm(np.asarray(out[key], np.float64), axis=-1)
        np.testing.assert_allclose(norms, 1.0, atol=1e-5)
    # The hypothesis's score is the mean of its views' scores.
    np.testing.assert_allclose(np.asarray(out["scores"]),
                               np.asarray(out["view_scores"], np.float64).mean(-1), atol=1e-6)
    # Views of one hypothesis have different scores (so the mean is not trivially equal).
    assert np.ptp(np.asarray(out["view_scores"]), axis=-1).min() > 1e-4


def test_changing_one_hypothesis_changes_only_its_outputs(model, inputs):
    real, renders = inputs
    base = forward(model, real, renders)
    other = renders.copy()
    k = 1
    other[:, k] = np.random.default_rng(1).uniform(size=other[:, k].shape)
    new = forward(model, real, other)
    for key in base:
        a, b = np.asarray(base[key]), np.asarray(new[key])
        keep = [i for i in range(K) if i != k]
        np.testing.assert_allclose(b[:, keep], a[:, keep], atol=1e-6, err_msg=key)
        assert np.abs(b[:, k] - a[:, k]).max() > 1e-4, key
    assert len(TRACES) == 1  # same shapes: traced once across the tests above


def test_real_crops_and_renders_share_one_encoder_and_decoder(model, inputs):
    # One parameter set: a single ViT in the module tree.
    vits = [m for _, m in nnx.iter_graph(model) if isinstance(m, ViT)]
    assert len(vits) == 1
    # With the cross-attention branches switched off (LayerScale 0) a render identical to the
    # real crop gets exactly the real crop's descriptors: both go through the same weights.
    real, renders = inputs
    same = nnx.clone(model)
    for block in same.cross_blocks:
        for ls in (block.ls1, block.ls2, block.ls3):
            ls.gamma[...] = jnp.zeros_like(ls.gamma[...])
    renders = renders.copy()
    renders[:, 0] = real / 255.0
    out = forward(same, real, renders)
    np.testing.assert_allclose(out["render_desc"][:, 0], out["real_desc"][:, 0], atol=1e-5)
    assert np.abs(np.asarray(out["render_desc"][:, 1] - out["real_desc"][:, 1])).max() > 0.1


def test_conditioned_levels_and_stems_keep_hypotheses_apart_and_streams_siamese(inputs):
    """The lever options (every DPT level of the real crop read from the cross-attention
    output, a pixel stem, a pretrained stem: ALIKED, whose stride-1 features are resized to
    the patch grid and the map; XFeat's stride-8 ones take the same path, and its refiner runs
    in tests/scripts/test_device.py): hypothesis k's outputs still depend on its render alone,
    and with the cross-attention branches off an identical render still gets the real crop's
    descriptors exactly."""
    cfg = get_refiner_config("tiny", conditioned_levels=4, pixel_features=8,
                             pretrained_stem="aliked", stem_descriptors=True, descriptor_dim=128)
    model = Refiner(cfg, rngs=nnx.Rngs(0))
    real, renders = inputs
    run = nnx.jit(lambda m, r, x: m(r, x))  # one compilation for the four calls
    # A fresh network's descriptors are the stem's features matched directly (stem_descriptors:
    # the head's correction starts at zero).
    fresh = run(model, real, renders)
    direct = nnx.jit(lambda s, r, x: ALIKEDDescriptors(s, cfg.output_size, sddh=False)(r, x))(
        model.stem, real, renders)
    for key in ("real_desc", "render_desc"):
        np.testing.assert_allclose(np.asarray(fresh[key]), np.asarray(direct[key]), atol=1e-5)
    # The stem's token projection and the descriptor head start at zero; make them read their
    # inputs, so that the test covers those paths too.
    for kernel in (model.stem_tokens.kernel, model.desc_head.kernel):
        assert not np.any(kernel[...])
        kernel[...] = jax.random.normal(jax.random.key(0), kernel.shape) * 0.1
    other = renders.copy()
    other[:, 1] = np.random.default_rng(1).uniform(size=other[:, 1].shape)
    a, b = run(model, real, renders), run(model, real, other)
    for key in a:
        np.testing.assert_allclose(np.asarray(b[key])[:, [0, 2]], np.asarray(a[key])[:, [0, 2]],
                                   atol=1e-6, err_msg=key)
        assert np.abs(np.asarray(b[key])[:, 1] - np.asarray(a[key])[:, 1]).max() > 1e-4, key
    for block in model.cross_blocks:
        for ls in (block.ls1, block.ls2, block.ls3):
            ls.gamma[...] = jnp.zeros_like(ls.gamma[...])
    same = renders.copy()
    same[:, 0] = real / 255.0
    out = run(model, real, same)
    np.testing.assert_allclose(out["render_desc"][:, 0], out["real_desc"][:, 0], atol=1e-5)
    with pytest.raises(ValueError, match="conditioned_levels must be 1 to 4"):
        get_refiner_config("tiny", conditioned_levels=5)
    with pytest.raises(ValueError, match="pixel_features must be >= 0"):
        get_refiner_config("tiny", pixel_features=-1)
    with pytest.raises(ValueError, match="'xfeat' needs a crop_size in multiples of 32.*use 96"):
        get_refiner_config("tiny", pretrained_stem="xfeat", crop_size=80, variant="tiny/8")
    with pytest.raises(ValueError, match="pretrained_stem must be one of"):
        get_refiner_config("tiny", pretrained_stem="dino")
    with pytest.raises(ValueError, match="stem_descriptors needs.*'aliked': 128.*got 'aliked'"):
        get_refiner_config("tiny", pretrained_stem="aliked", stem_descriptors=True)


def test_input_errors_name_the_expected_shapes(model, inputs):
    real, renders = inputs
    with pytest.raises(ValueError, match=r"real crops must be \[B, V, 64, 64, 3\]"):
        nnx.eval_shape(lambda m: m(real[..., :32, :32, :], renders), model)
    with pytest.raises(ValueError, match="renders must be"):
        nnx.eval_shape(lambda m: m(real, renders[:, :, :1]), model)


def test_refiner_sizes_and_config_errors():
    assert set(REFINER_SIZES) == {"tiny", "cpu", "small", "paper"}
    paper = get_refiner_config("paper")
    assert (paper.variant, paper.crop_size, paper.num_registers, paper.output_size) == (
        "L/14", 224, 4, 64)
    assert paper.layerscale_init == 1e-5 and paper.remat and paper.dtype == jnp.bfloat16
    assert paper.encoder_hooks == (5, 11, 17, 23)  # DPT-Large's hooks
    assert get_refiner_config("small").encoder_hooks == (2, 5, 8, 11)
    assert CFG.encoder_hooks == (0, 0, 1, 1)
    assert CFG.vit == ViTConfig.from_variant("tiny/16", image_size=64, num_registers=4,
                                             layerscale_init=0.1)
    assert RefinerConfig(variant="S/14", crop_size=112).output_size == 32  # 4 x grid
    assert RefinerConfig(**paper.to_dict()) == paper
    with pytest.raises(ValueError, match="use 224"):
        RefinerConfig(variant="L/14", crop_size=220)
    with pytest.raises(ValueError, match="num_registers must be >= 1"):
        RefinerConfig(num_registers=0)
    with pytest.raises(ValueError, match="known sizes"):
        get_refiner_config("huge")


def paper_param_count():
    """Hand count of the paper refiner (L/14, 224 px, 4 registers, LayerScale, 8 cross-attention
    blocks, DPT with F = 256 and levels (256, 512, 1024, 1024), C = 128)."""
    D, M, L, p, P, R, C, F, X = 1024, 4096, 24, 14, 256, 4, 128, 256, 8
    d0, d1, d2, d3 = 256, 512, 1024, 1024
    lin = D * D + D
    encoder = (p * p * 3 * D + D + P * D + R * D  # patch embedding, position embedding, registers
               + L * (2 * 2 * D + 4 * lin + 2 * D * M + M + D + 2 * D)  # LN, attn, MLP, LS
               + 2 * D)  # final LN
    cross = X * (4 * 2 * D + 8 * lin + 2 * D * M + M + D + 3 * D)  # 4 LN, 2 attn, MLP, 3 LS
    top = 2 * D + D + 1  # LayerNorm of the fourth level, score head
    rcu = 2 * (9 * F * F + F)
    dpt = (sum(D * d + d for d in (d0, d1, d2, d3))  # 1x1 projections
           + 16 * d0 * d0 + d0 + 4 * d1 * d1 + d1 + 4 * d3 * d3 + d3  # resampling
           + 9 * F * (d0 + d1 + d2 + d3)  # 3x3 convolutions to F, no bias
           + 7 * rcu + 4 * (F * F + F)  # 4 fusion blocks (the coarsest without skip unit)
           + 9 * F * (F // 2) + F // 2 + 9 * (F // 2) ** 2 + F // 2)  # head
    heads = (F // 2) * C + C + F // 2 + 1  # descriptor and mask 1x1 convolutions
    return encoder + cross + top + dpt + heads


def test_paper_size_parameter_count_and_memory_plan():
    expected = paper_param_count()
    assert expected == 462_298_626
    plan = memory_plan()  # paper, 64 instances, 5 hypotheses, 1 view, 1 device
    assert plan["parameters"] == plan["gradients"] == 4 * expected  # float32 storage
    assert plan["optimizer"] == 8 * expected  # Adam's two float32 moments
    assert plan["inputs"] == 64 * 6 * 224 * 224 * 3
    assert plan["matching_logits"] == 2 * 64 * 5 * 4096**2 * 4
    # With remat, the 24 encoder blocks keep at least their bf16 inputs for 6 x 64 images.
    assert plan["activations_saved"] > 24 * 384 * 260 * 1024 * 2
    assert plan["total"] == sum(v for k, v in plan.items() if k not in ("total",
                                                                         "matching_logits"))


def test_saved_residuals_against_hand_count():
    # sum(sin(x @ w)): the backward keeps cos(x @ w) [N, M] float32, and x (an input, not
    # counted) for the gradient of w.
    w = jax.ShapeDtypeStruct((8, 16), jnp.float32)
    x = jax.ShapeDtypeStruct((32, 8), jnp.float32)
    assert _saved_residual_bytes(lambda p, a: jnp.sin(a @ p), w, x) == 32 * 16 * 4


def test_memory_plan_scales_with_devices_and_remat(model):
    one = memory_plan(CFG, instances=8, devices=1)
    four = memory_plan(CFG, instances=8, devices=4)
    assert four["parameters"] == -(-one["parameters"] // 4)
    assert four["inputs"] * 4 == one["inputs"]
    assert four["activations_saved"] < one["activations_saved"] / 3
    remat = memory_plan(RefinerConfig(**{**CFG.to_dict(), "remat": True}), instances=8)
    assert remat["activations_saved"] < one["activations_saved"]
    assert one["parameters"] == 4 * count_params(model)


def test_bfloat16_compute_returns_float32_and_odd_grids_work():
    # Shapes only (nnx.eval_shape): bf16 compute, and a 3 x 3 patch grid (DPT's coarsest level
    # is 2 x 2 and is resized back to 3 x 3), with a map size that is not 4 x the grid.
    cfg = get_refiner_config("tiny", crop_size=48, output_size=20, dtype="bfloat16")
    real = jax.ShapeDtypeStruct((2, 1, 48, 48, 3), jnp.uint8)
    renders = jax.ShapeDtypeStruct((2, 4, 1, 48, 48, 3), jnp.float32)
    out = nnx.eval_shape(lambda r, q: Refiner(cfg, rngs=nnx.Rngs(0))(r, q), real, renders)
    assert out["real_desc"].shape == (2, 4, 1, 20, 20, 32)
    assert out["mask_logits"].shape == (2, 4, 1, 20, 20)
    assert all(v.dtype == jnp.float32 for v in out.values())
