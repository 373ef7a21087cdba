"""ViT backbone: variant table, parameter count, position embeddings, attention, extra tokens."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from threept_jax.models.configs import DetectorConfig, ViTConfig, decode_variant
from threept_jax.models.vit import (
    Attention,
    CrossAttentionBlock,
    ViT,
    count_params,
    posemb_sincos_2d,
    resize_posemb,
)


def vit_param_count(width, depth, mlp, patch, num_patches, registers=0):
    """Hand count of a class-token-free pre-LN ViT (no head)."""
    patch_embed = patch * patch * 3 * width + width
    posemb = num_patches * width
    block = 2 * 2 * width + 4 * (width * width + width) + 2 * width * mlp + mlp + width
    return patch_embed + posemb + registers * width + depth * block + 2 * width


@pytest.fixture(scope="module")
def tiny_vit():
    # Same sizes as the tiny detector's tower, so both files share compiled initialisers.
    return ViT(ViTConfig.from_variant("tiny", image_size=64, num_registers=1), rngs=nnx.Rngs(0))


@pytest.mark.parametrize("variant, expected", [
    ("B/16", (768, 12, 12, 3072, 16)),
    ("S/16", (384, 12, 6, 1536, 16)),
    ("L/14", (1024, 24, 16, 4096, 14)),
    ("tiny", (64, 2, 2, 256, 16)),
    ("tiny/8", (64, 2, 2, 256, 8)),
])
def test_decode_variant(variant, expected):
    d = decode_variant(variant)
    assert (d["width"], d["depth"], d["num_heads"], d["mlp_dim"], d["patch_size"]) == expected


@pytest.mark.parametrize("bad, msg", [("X/16", "unknown ViT size"), ("B", "needs a patch size"),
                                      ("B/x", "positive integer"), ("", "string")])
def test_decode_variant_errors(bad, msg):
    with pytest.raises(ValueError, match=msg):
        decode_variant(bad)


def test_config_errors_name_the_fix():
    with pytest.raises(ValueError, match="use 518"):
        DetectorConfig(variant="L/14", image_size=512)
    with pytest.raises(ValueError, match="divisible"):
        ViTConfig(width=65, depth=1, num_heads=2, mlp_dim=8, patch_size=4, image_size=8)
    assert DetectorConfig(variant="L/14").image_size == 518
    assert DetectorConfig(variant="B/16").image_size == 512


def test_b16_parameter_count_matches_hand_count():
    # ViT-B/16 at 224 without class token and head: 85.8M (86.6M with the 1000-class head).
    abstract = nnx.eval_shape(lambda: ViT(ViTConfig.from_variant("B/16"), rngs=nnx.Rngs(0)))
    expected = vit_param_count(768, 12, 3072, 16, 196)
    assert expected == 85_797_120
    assert count_params(abstract) == expected


def test_learned_posemb_exact_at_native_grid_and_bilinear_elsewhere(tiny_vit):
    np.testing.assert_array_equal(np.asarray(tiny_vit.position_embedding((4, 4))),
                                  np.asarray(tiny_vit.posemb[...]))
    # 2x2 -> 4x4 upsampling against a float64 half-pixel-centre bilinear reference.
    pe = np.random.default_rng(0).normal(size=(4, 3))
    got = np.asarray(resize_posemb(jnp.asarray(pe, jnp.float32), (2, 2), (4, 4))).reshape(4, 4, 3)
    src = pe.reshape(2, 2, 3)
    ref = np.zeros((4, 4, 3))
    for i in range(4):
        for j in range(4):
            y = np.clip((i + 0.5) / 2 - 0.5, 0, 1)
            x = np.clip((j + 0.5) / 2 - 0.5, 0, 1)
            y0, x0 = int(np.floor(y)), int(np.floor(x))
            y1, x1 = min(y0 + 1, 1), min(x0 + 1, 1)
            fy, fx = y - y0, x - x0
            ref[i, j] = ((1 - fy) * ((1 - fx) * src[y0, x0] + fx * src[y0, x1])
                         + fy * ((1 - fx) * src[y1, x0] + fx * src[y1, x1]))
    np.testing.assert_allclose(got, ref, atol=1e-6)


def test_sincos_posemb_depends_only_on_offset():
    pe = np.asarray(posemb_sincos_2d(6, 7, 32), np.float64).reshape(6, 7, 32)
    a = pe[1, 2] @ pe[3, 5]
    b = pe[2, 0] @ pe[4, 3]
    np.testing.assert_allclose(a, b, rtol=1e-5)
    assert pe.shape == (6, 7, 32)


def test_attention_matches_float64_reference_with_mask():
    att = Attention(16, 4, dtype=jnp.float32, param_dtype=jnp.float32, rngs=nnx.Rngs(1))
    rng = np.random.default_rng(0)
    x = rng.normal(size=(2, 3, 16)).astype(np.float32)
    ctx = rng.normal(size=(2, 5, 16)).astype(np.float32)
    mask = np.array([[1, 1, 1, 0, 0], [1, 0, 1, 1, 1]], bool)
    got = np.asarray(nnx.jit(lambda m, *a: m(*a))(att, x, ctx, mask))

    def lin(mod, v):
        k = np.asarray(mod.kernel[...], np.float64)
        b = np.asarray(mod.bias[...], np.float64)
        n = k.ndim - b.ndim  # number of contracted input axes
        return np.tensordot(v, k, axes=(list(range(v.ndim - n, v.ndim)), list(range(n)))) + b

    q, k, v = (lin(m, a.astype(np.float64)) for m, a in
               ((att.query, x), (att.key, ctx), (att.value, ctx)))  # [B, N, H, Dh]
    logits = np.einsum("bnhd,bshd->bhns", q, k) / np.sqrt(4)
    logits = np.where(mask[:, None, None], logits, -np.inf)
    w = np.exp(logits - logits.max(-1, keepdims=True))
    w /= w.sum(-1, keepdims=True)
    y = np.einsum("bhns,bshd->bnhd", w, v)
    ref = lin(att.out, y)
    np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-5)


@nnx.jit
def _forward(model, x, extra=None, extra_mask=None):
    return model(x, extra, extra_mask)


def test_extra_tokens_join_attention(tiny_vit):
    x = jax.random.uniform(jax.random.key(0), (2, 32, 32, 3))
    extra = jax.random.normal(jax.random.key(1), (2, 3, 64))
    plain = _forward(tiny_vit, x)
    fused = _forward(tiny_vit, x, extra, jnp.ones((2, 3), bool))
    hidden = _forward(tiny_vit, x, extra, jnp.zeros((2, 3), bool))
    assert fused["patch_tokens"].shape == (2, 4, 64)
    assert fused["extra_tokens"].shape == (2, 3, 64)
    assert fused["register_tokens"].shape == (2, 1, 64)
    # Masked extra tokens must not influence the patches; unmasked ones must.
    np.testing.assert_allclose(hidden["patch_tokens"], plain["patch_tokens"], atol=1e-5)
    assert np.abs(np.asarray(fused["patch_tokens"]) - plain["patch_tokens"]).max() > 1e-3
    # Any patch-aligned size works (position embedding follows the grid).
    half = nnx.eval_shape(lambda m, v: m(v), tiny_vit, x[:, :16])
    assert half["patch_tokens"].shape == (2, 2, 64)
    with pytest.raises(ValueError, match="multiple of the patch size"):
        nnx.eval_shape(lambda m, v: m(v), tiny_vit, x[:, :20])


def test_bfloat16_matches_float32_and_remat_checkpoints_blocks(tiny_vit):
    x = jax.random.uniform(jax.random.key(0), (2, 32, 32, 3))
    kw = dict(image_size=64, num_registers=1)
    # Same seed as the fixture, so same float32 parameters; only the compute dtype differs.
    bf = ViT(ViTConfig.from_variant("tiny", dtype="bfloat16", **kw), rngs=nnx.Rngs(0))
    out = _forward(bf, x)["patch_tokens"]
    assert out.dtype == jnp.bfloat16 and np.isfinite(np.asarray(out, np.float32)).all()
    assert bf.blocks[0].mlp.fc1.kernel[...].dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(out, np.float32), _forward(tiny_vit, x)["patch_tokens"],
                               atol=0.1)
    # remat wraps every block in a checkpoint in the backward pass (nothing else changes).
    rem = ViT(ViTConfig.from_variant("tiny", remat=True, **kw), rngs=nnx.Rngs(0))

    def num_checkpoints(model):
        graphdef, params = nnx.split(model)

        def loss(p):
            return jnp.sum(nnx.merge(graphdef, p)(x)["patch_tokens"])

        eqns = jax.make_jaxpr(jax.grad(loss))(params).jaxpr.eqns
        return sum(e.primitive.name in ("remat2", "checkpoint") for e in eqns)

    assert num_checkpoints(rem) == 2 and num_checkpoints(tiny_vit) == 0


def test_layerscale_off_builds_nothing_and_on_scales_each_branch(tiny_vit):
    x = jax.random.uniform(jax.random.key(0), (2, 32, 32, 3))
    kw = dict(image_size=64, num_registers=1)
    # Off (the default, the detector's setting): no gamma parameters, the hand count holds.
    assert ViTConfig.from_variant("tiny").layerscale_init is None
    assert DetectorConfig(variant="tiny").vit.layerscale_init is None
    paths = [p for p, _ in nnx.iter_graph(tiny_vit)]
    assert not any("ls1" in map(str, p) for p in paths)
    assert count_params(tiny_vit) == vit_param_count(64, 2, 256, 16, 16, registers=1)
    # On: two D-vectors per block; LayerScale draws no random numbers, so the same seed gives
    # the same other parameters.
    one = ViT(ViTConfig.from_variant("tiny", layerscale_init=1.0, **kw), rngs=nnx.Rngs(0))
    assert count_params(one) == count_params(tiny_vit) + 2 * 2 * 64
    np.testing.assert_array_equal(one.blocks[1].ls2.gamma[...], np.ones(64, np.float32))
    # gamma = 1 multiplies exactly: outputs equal the LayerScale-free ViT bit for bit.
    np.testing.assert_array_equal(_forward(one, x)["patch_tokens"],
                                  _forward(tiny_vit, x)["patch_tokens"])
    # gamma = 0 makes every block the identity: the output is the final LayerNorm of the
    # embedded patches (an independent composition of the model's first and last layers).
    zero = nnx.clone(one)
    for block in zero.blocks:
        for ls in (block.ls1, block.ls2):
            ls.gamma[...] = jnp.zeros(64)
    expected = zero.norm(zero.embed_patches(x))
    np.testing.assert_allclose(_forward(zero, x)["patch_tokens"], expected, atol=1e-6)
    with pytest.raises(ValueError, match="layerscale_init must be > 0"):
        ViTConfig.from_variant("tiny", layerscale_init=0.0)


def test_intermediate_layers_are_normed_block_outputs(tiny_vit):
    x = jax.random.uniform(jax.random.key(0), (2, 32, 32, 3))
    out = _forward_layers(tiny_vit, x)
    assert len(out["layers"]) == 2
    # The last block's output after the final norm is the patch-token output itself.
    np.testing.assert_array_equal(out["layers"][1], out["patch_tokens"])
    # Block 0's output, composed by hand from the embedded patches and the register.
    tokens = jnp.concatenate([tiny_vit.embed_patches(x),
                              jnp.broadcast_to(tiny_vit.registers[...][None], (2, 1, 64))], 1)
    expected = tiny_vit.norm(tiny_vit.blocks[0](tokens))[:, :4]
    np.testing.assert_allclose(out["layers"][0], expected, atol=1e-5)
    with pytest.raises(ValueError, match=r"block indices in \[0, 2\)"):
        nnx.eval_shape(lambda m, v: m(v, layers=(2,)), tiny_vit, x)


@nnx.jit
def _forward_layers(model, x):
    return model(x, layers=(0, 1))


def test_cross_attention_block_matches_hand_composition():
    cfg = ViTConfig.from_variant("tiny", image_size=32, layerscale_init=0.5)
    block = CrossAttentionBlock(cfg, rngs=nnx.Rngs(3))
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.normal(size=(2, 5, 64)), jnp.float32)
    ctx = jnp.asarray(rng.normal(size=(2, 7, 64)), jnp.float32)
    got = block(x, ctx)
    y = x + 0.5 * block.attn(block.norm1(x))
    y = y + 0.5 * block.cross_attn(block.norm2(y), block.norm_context(ctx))
    y = y + 0.5 * block.mlp(block.norm3(y))
    np.testing.assert_allclose(got, y, atol=1e-5)
    # Queries see the context: changing a context token changes every query's output.
    moved = ctx.at[:, 0].set(jnp.asarray(rng.normal(size=(2, 64)), jnp.float32))
    assert np.abs(np.asarray(block(x, moved) - got)).max(axis=-1).min() > 1e-4


def test_conv_stem_parameters_shapes_and_receptive_field():
    """``stem="conv"``: log2(patch) 3x3 stride-2 convolutions with LayerNorm (channels doubling
    up to the width, at least 16), then a 1x1 projection; counted by hand. A token's receptive
    field is wider than its patch (a pixel changes the tokens of the next patches too) and
    local (no norm over the image): tokens far from the pixel do not change."""
    width, patch = 64, 16
    cfg = ViTConfig.from_variant("tiny/16", image_size=64, stem="conv")
    vit = ViT(cfg, rngs=nnx.Rngs(0))
    channels = [16, 16, 32, 64]
    convs = sum(9 * c_in * c_out + c_out for c_in, c_out in zip([3, *channels[:-1]], channels))
    stem = convs + sum(2 * c for c in channels) + channels[-1] * width + width
    plain = vit_param_count(width, 2, 256, patch, num_patches=16)
    assert count_params(vit) == plain - (patch * patch * 3 * width + width) + stem
    img = np.zeros((1, 64, 64, 3), np.float32)
    base = np.asarray(vit.embed_patches(img))[0].reshape(4, 4, width)
    img[0, 32, 32] = 1.0  # top-left pixel of patch (2, 2)
    moved = np.abs(np.asarray(vit.embed_patches(img))[0].reshape(4, 4, width) - base).max(-1)
    # 'SAME' stride-2 3x3 windows start at 2i: the pixel reaches output 2i = 32 and 2i + 2 = 32
    # of the first layer, i.e. tokens 1 and 2 after four layers.
    assert moved[1, 1] > 0 and moved[2, 2] > 0
    assert np.all(moved[0, :] == 0) and np.all(moved[:, 0] == 0) and moved[3, 3] == 0
    with pytest.raises(ValueError, match="power of two"):
        ViTConfig.from_variant("L/14", stem="conv")
    with pytest.raises(ValueError, match="stem must be"):
        ViTConfig.from_variant("tiny", stem="resnet")
