"""3PT-D detector: full-size shapes without compute, tiny model forward, initial heads."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from threept_jax.losses.detection import DetectorLossConfig, detection_loss, make_targets
from threept_jax.models.configs import DetectorConfig
from threept_jax.models.detector import Detector, boxes_to_pixels, orientation_scores
from threept_jax.models.vit import count_params

TINY = DetectorConfig(variant="tiny", image_size=64, render_size=32, tokens_per_view=2,
                      embed_dim=16, num_registers=1)


def vit_param_count(width, depth, mlp, patch, num_patches, registers=0):
    """Hand count of a class-token-free pre-LN ViT (no head)."""
    patch_embed = patch * patch * 3 * width + width
    block = 2 * 2 * width + 4 * (width * width + width) + 2 * width * mlp + mlp + width
    return patch_embed + num_patches * width + registers * width + depth * block + 2 * width


@pytest.mark.parametrize("variant, width, depth, mlp, patch, tile", [
    ("S/16", 384, 12, 1536, 16, 512),
    ("B/16", 768, 12, 3072, 16, 512),
    ("L/14", 1024, 24, 4096, 14, 518),
])
def test_full_size_shapes_without_compute(variant, width, depth, mlp, patch, tile):
    cfg = DetectorConfig(variant=variant)
    assert cfg.image_size == tile
    b, o, t = 2, 3, 5140
    # The object-tower stages trace the same blocks again; checking them on the smallest
    # variant keeps this test fast.
    with_object_tower = variant == "S/16"
    counts = {}

    def run(tiles, priors, templates, bank):
        model = Detector(cfg, rngs=nnx.Rngs(0))
        counts["tower"] = count_params(model.image_tower)
        counts["shared"] = model.object_tower is model.image_tower
        out = {"detect": model(tiles, jnp.zeros((b, cfg.num_prior_tokens, width)), bank)}
        if with_object_tower:
            out["prior_tokens"] = model.embed_object(priors)
            out["bank"] = model.embed_templates(templates)
        return out

    out = jax.eval_shape(
        run, jax.ShapeDtypeStruct((b, tile, tile, 3), jnp.float32),
        jax.ShapeDtypeStruct((o, 12, 224, 224, 3), jnp.float32),
        jax.ShapeDtypeStruct((o, 2, 224, 224, 3), jnp.float32),
        jax.ShapeDtypeStruct((b, t, width), jnp.float32))
    p = (tile // patch) ** 2
    det = out["detect"]
    assert det["boxes"].shape == (b, p, 4)
    assert det["presence_logits"].shape == (b, p)
    assert det["embeddings"].shape == (b, p, width)
    assert det["detection_logits"].shape == (b, p)
    assert det["logit_scale"].shape == ()
    if with_object_tower:
        assert out["prior_tokens"].shape == (o, 12 * 4, width)
        assert out["bank"].shape == (o, 2, width)
    assert counts["tower"] == vit_param_count(width, depth, mlp, patch, p)
    assert counts["shared"]


def test_separate_towers_add_one_backbone():
    shared = nnx.eval_shape(lambda: Detector(TINY, rngs=nnx.Rngs(0)))
    cfg = dataclasses.replace(TINY, share_backbone=False)
    split = nnx.eval_shape(lambda: Detector(cfg, rngs=nnx.Rngs(0)))
    assert split.object_tower is not split.image_tower
    assert count_params(split) - count_params(shared) == vit_param_count(64, 2, 256, 16, 16, 1)


@pytest.fixture(scope="module")
def tiny():
    model = Detector(TINY, rngs=nnx.Rngs(0))
    k = jax.random.split(jax.random.key(0), 3)
    priors = jax.random.uniform(k[0], (2, 12, 32, 32, 3))
    templates = jax.random.uniform(k[1], (2, 7, 32, 32, 3))
    tiles = jax.random.uniform(k[2], (2, 64, 64, 3))
    return model, priors, templates, tiles


@nnx.jit
def _pipeline(model, priors, templates, tiles):
    prior_tokens = model.embed_object(priors)
    bank = model.embed_templates(templates)
    return prior_tokens, bank, model(tiles, prior_tokens, bank)


def test_tiny_forward_shapes_finite_and_initial_heads(tiny):
    model, priors, templates, tiles = tiny
    prior_tokens, bank, out = _pipeline(model, priors, templates, tiles)
    assert prior_tokens.shape == (2, 24, 64)
    assert bank.shape == (2, 7, 16)
    assert out["boxes"].shape == (2, 16, 4) and out["embeddings"].shape == (2, 16, 16)
    for v in (prior_tokens, bank, *out.values()):
        assert np.isfinite(np.asarray(v)).all()
    np.testing.assert_allclose(np.linalg.norm(bank, axis=-1), 1.0, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(out["embeddings"], axis=-1), 1.0, atol=1e-5)
    # Presence starts at the 0.01 prior on every patch.
    np.testing.assert_allclose(out["presence_logits"], np.log(0.01 / 0.99), atol=1e-5)
    # Boxes start at each patch's own cell: centres ((j + .5) / 4, (i + .5) / 4), size 1/4.
    i, j = np.divmod(np.arange(16), 4)
    prior = np.stack([(j + 0.5) / 4, (i + 0.5) / 4, np.full(16, 0.25), np.full(16, 0.25)], -1)
    np.testing.assert_allclose(out["boxes"], np.broadcast_to(prior, (2, 16, 4)), atol=1e-6)
    # Detection logit = max over templates of scale * cos + bias, never above the prior.
    e = np.asarray(out["embeddings"], np.float64)
    cos = np.einsum("bpe,bte->bpt", e, np.asarray(bank, np.float64))
    ref = 10.0 * cos.max(-1) + np.log(0.01 / 0.99) - 10.0
    np.testing.assert_allclose(out["detection_logits"], ref, atol=1e-4)
    assert np.max(out["detection_logits"]) <= np.log(0.01 / 0.99) + 1e-5


def test_templates_chunked_equal_unchunked_and_prior_changes_output(tiny):
    model, priors, templates, tiles = tiny
    _, bank, out = _pipeline(model, priors, templates, tiles)
    bank_chunked = nnx.jit(lambda m, x: m.embed_templates(x, chunk_size=3))(model, templates)
    np.testing.assert_allclose(bank_chunked, bank, atol=1e-5)
    # Early fusion: a different object (other prior renders) changes the hypotheses.
    _, _, other = _pipeline(model, priors[::-1], templates, tiles)
    assert np.abs(np.asarray(other["embeddings"]) - out["embeddings"]).max() > 1e-4


def test_orientation_scores_are_cosines():
    rng = np.random.default_rng(0)
    e = rng.normal(size=(2, 3, 5))
    bank = rng.normal(size=(4, 5))
    bank /= np.linalg.norm(bank, axis=-1, keepdims=True)
    ref = np.einsum("bpe,te->bpt", e / np.linalg.norm(e, axis=-1, keepdims=True), bank)
    got = orientation_scores(jnp.asarray(e), jnp.asarray(bank))
    np.testing.assert_allclose(got, ref, atol=1e-6)
    per_tile = np.stack([bank, bank[::-1]])
    got = orientation_scores(jnp.asarray(e), jnp.asarray(per_tile))
    np.testing.assert_allclose(got[1], ref[1][:, ::-1], atol=1e-6)
    with pytest.raises(ValueError, match="template_bank"):
        orientation_scores(jnp.asarray(e), jnp.zeros((3, 4, 5)))


def test_decode_helpers_hand_values():
    boxes = jnp.asarray([[0.5, 0.25, 0.2, 0.5]])
    np.testing.assert_allclose(boxes_to_pixels(boxes, (100, 200)), [[80.0, 0.0, 120.0, 50.0]])


def test_input_errors_name_the_fix(tiny):
    model, priors, _, tiles = tiny
    with pytest.raises(ValueError, match="12 prior views"):
        nnx.eval_shape(lambda m, x: m.embed_object(x), model, priors[:, :5])
    with pytest.raises(ValueError, match="render_size=32"):
        nnx.eval_shape(lambda m, x: m.embed_templates(x), model, jnp.zeros((1, 2, 48, 48, 3)))
    with pytest.raises(ValueError, match="embed_object"):
        nnx.eval_shape(lambda m, x: m.detect(x, jnp.zeros((2, 5, 64))), model, tiles)


def test_pipeline_compiles_once(tiny):
    model, _, _, tiles = tiny
    traces = []

    @nnx.jit
    def detect(m, x, p):
        traces.append(1)
        return m.detect(x, p)

    prior_tokens = jnp.zeros((2, 24, 64))
    detect(model, tiles, prior_tokens)
    detect(model, tiles * 0.5, prior_tokens + 1.0)
    assert len(traces) == 1


def test_training_loss_gradients_reach_every_head(tiny):
    model, priors, templates, tiles = tiny
    targets = jax.jit(make_targets, static_argnums=1)(
        np.asarray([[[4.0, 4.0, 30.0, 40.0]], [[10.0, 20.0, 60.0, 50.0]]]), (64, 64),
        np.ones((2, 1), bool), template_index=np.asarray([[3], [5]]))
    cfg = DetectorLossConfig()

    # Differentiate the heads only: backbone gradients are plain backprop, while reaching the
    # prior pooling needs the path through the image tower's attention to the prior tokens
    # (early fusion) and the template pooling the path through the template bank. Leaving the
    # backbone out keeps the compiled backward pass small.
    heads = nnx.All(nnx.Param, nnx.Not(nnx.PathContains("image_tower")))

    @nnx.jit
    def step(m):
        def loss_fn(m):
            out = m(tiles, m.embed_object(priors), m.embed_templates(templates))
            return detection_loss(out, targets, cfg)

        return nnx.value_and_grad(loss_fn, argnums=nnx.DiffState(0, heads), has_aux=True)(m)

    (loss, metrics), grads = step(model)
    assert np.isfinite(float(loss)) and float(metrics["num_boxes"]) == 2.0
    leaves = jax.tree_util.tree_leaves(nnx.state(grads))
    assert leaves and all(np.isfinite(np.asarray(g)).all() for g in leaves)

    def norm(x):
        return float(np.linalg.norm(np.asarray(x[...])))

    for name, g in [("prior_probes", grads.prior_pool.probes),
                    ("prior_proj", grads.prior_proj.kernel),
                    ("prior_slots", grads.prior_slot_embed),
                    ("template_probes", grads.template_pool.probes),
                    ("embed_head", grads.embed_head.kernel),
                    ("logit_scale", grads.log_logit_scale),
                    ("logit_bias", grads.logit_bias),
                    ("presence_out", grads.presence_head.out.kernel),
                    ("box_out", grads.box_head.out.kernel)]:
        assert norm(g) > 0, name



def test_box_head_reaches_amodal_boxes_past_the_tile():
    """Issue 13 item 1.4: the decoded box spans centres (-0.5, 1.5) and sizes (0, 2) tile sides
    (hand-derived from low + (high - low) * sigmoid), so a target half outside the tile (centre
    on the tile edge, 1.2 tiles wide) is reachable; raw 0 is the patch's own cell."""
    from threept_jax.models.heads import decode_boxes

    gh, gw = 2, 3
    big = np.full((gh * gw, 4), 40.0, np.float32)
    np.testing.assert_allclose(decode_boxes(big, gh, gw), np.tile([1.5, 1.5, 2.0, 2.0], (6, 1)))
    np.testing.assert_allclose(decode_boxes(-big, gh, gw), np.tile([-0.5, -0.5, 0, 0], (6, 1)),
                               atol=1e-6)
    i, j = np.divmod(np.arange(gh * gw), gw)
    cell = np.stack([(j + 0.5) / gw, (i + 0.5) / gh, np.full(6, 1 / gw), np.full(6, 1 / gh)], -1)
    np.testing.assert_allclose(decode_boxes(np.zeros((6, 4), np.float32), gh, gw), cell,
                               atol=1e-6)
    target = np.array([1.0, 0.5, 1.2, 0.4])
    p = (target - [-0.5, -0.5, 0.0, 0.0]) / 2.0
    cell_p = (cell[0] - [-0.5, -0.5, 0.0, 0.0]) / 2.0
    raw = np.log(p / (1 - p)) - np.log(cell_p / (1 - cell_p))  # logit(target) - logit(cell)
    got = decode_boxes(np.tile(raw, (6, 1)).astype(np.float32), gh, gw)[0]
    np.testing.assert_allclose(got, target, atol=1e-5)
