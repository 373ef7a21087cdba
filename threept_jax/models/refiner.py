"""3PT-R: the render-and-compare refiner network (paper section 3.3, docs/design.md section 1.3).

Per object instance: V real crops and K x V renders of the CAD model (one per hypothesis and
view, drawn into the same crops). The network:

1. **One shared encoder** (DINOv2-style ViT: register tokens, LayerScale; :class:`ViT`) embeds
   the real crops and the renders in one call, so both go through the same weights.
2. **Cross-attention** (CroCo decoder blocks, :class:`CrossAttentionBlock`, as Co-Op does):
   the tokens (patches and registers) of real view v are the queries, and under hypothesis k
   they attend to the tokens of *the render of view v under hypothesis k only*. Own view, not
   all V views, because (a) the descriptors serve 2D-2D matching between real view v and
   render v, which share one crop camera, so the render of view v holds every token a real
   pixel can correspond to; (b) the computation per (hypothesis, view) pair then does not
   depend on V, so a network trained on one view runs unchanged on 3 or 8 (and the cost grows
   linearly in V, not quadratically); multi-view evidence enters where it is geometric, in the
   multi-view PnP of the refinement step and in the score mean over views. The renders' tokens
   are not updated by cross-attention.
3. **A DPT decoder** (:mod:`threept_jax.models.dpt`, shared by both streams) reads four levels:
   encoder blocks ``cfg.encoder_hooks[:3]`` and, as the fourth, the cross-attention output for
   the real crop and the last encoder block for a render, both through one LayerNorm. With
   LayerScale the cross-attention blocks start near the identity, so at initialisation the
   real and the render streams are (nearly) the same Siamese function and identical images
   get (nearly) identical descriptors. 1x1 heads give
   C-dimensional descriptors (L2-normalised: F for the real crop, Z for each render) and, for
   the real crop only, a mask logit per pixel. The maps have side h = ``cfg.output_size``
   (default 4 x the patch grid: 64 for 224 px crops at /14); pixel (i, j) is the crop point
   ((j + 0.5) H / h - 0.5, (i + 0.5) H / h - 0.5).
4. **Scores**: the first register token of the real view after cross-attention, through a
   linear layer, is the score logit of that (hypothesis, view); a hypothesis's score is the
   mean over its views.

Two optional stems read the crops themselves (``RefinerConfig``): ``pixel_features``, two
3 x 3 convolutions joined to DPT's output, and ``pretrained_stem``, a pretrained network
(``"xfeat"``: :mod:`threept_jax.models.xfeat`, stride-8 features; ``"aliked"``:
:mod:`threept_jax.models.aliked`, stride-1 features; BatchNorms folded) whose features are
added to the patch embeddings (a linear layer that starts at zero) and joined to DPT's output
too.

Every output of hypothesis k is computed from the real crops and the renders of hypothesis k
alone (no normalisation or attention across hypotheses), so hypotheses are independent by
construction. Shapes: B instances, K hypotheses, V views, H = W crop side, h = w map side,
C descriptor dimension, P patches, R registers, D width.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from threept_jax.models.aliked import ALIKED
from threept_jax.models.configs import STEM_CHANNELS, RefinerConfig, get_refiner_config
from threept_jax.models.dpt import DPT, resize
from threept_jax.models.heads import unit_range, unit_vectors
from threept_jax.models.vit import (
    CrossAttentionBlock,
    EncoderBlock,
    LayerNorm,
    ViT,
    apply_cross_block,
    count_params,
)
from threept_jax.models.xfeat import XFeat

#: Each pretrained stem (``RefinerConfig.pretrained_stem``): its network in the folded form a
#: stem trains in (the channels of its ``features``: ``configs.STEM_CHANNELS``).
STEMS = {"xfeat": lambda rngs: XFeat(folded=True, rngs=rngs),
         "aliked": lambda rngs: ALIKED(folded=True, rngs=rngs)}

Array = jax.Array


class Refiner(nnx.Module):
    """3PT-R network: ``Refiner(cfg, rngs=nnx.Rngs(0))(real, renders) -> dict``.

    ``real`` [B, V, H, W, 3] and ``renders`` [B, K, V, H, W, 3], uint8 or float in [0, 1], with
    H = W = ``cfg.crop_size``. Returns float32 arrays: ``real_desc`` [B, K, V, h, w, C] and
    ``render_desc`` [B, K, V, h, w, C] (unit vectors), ``mask_logits`` [B, K, V, h, w] (the
    object's visible mask in the real crop), ``view_scores`` [B, K, V] and ``scores`` [B, K]
    (the mean of ``view_scores`` over views). See the module docstring for the architecture.
    """

    def __init__(self, cfg: RefinerConfig, *, rngs: nnx.Rngs):
        self.cfg = cfg
        vit = cfg.vit
        kw = dict(dtype=cfg.dtype, param_dtype=cfg.param_dtype, rngs=rngs)
        self.encoder = ViT(vit, rngs=rngs)
        self.cross_blocks = nnx.List([CrossAttentionBlock(vit, rngs=rngs)
                                      for _ in range(cfg.cross_attention_layers)])
        # Normalises the fourth DPT level of both streams (and the score token).
        self.top_norm = LayerNorm(cfg.width, epsilon=vit.layernorm_epsilon, **kw)
        self.score_head = nnx.Linear(cfg.width, 1, **kw)
        self.dpt = DPT(cfg.width, cfg.dpt_dims, cfg.dpt_features, cfg.output_size,
                       remat=cfg.remat, **kw)
        head_in = cfg.dpt_features // 2
        conv = dict(kernel_size=(3, 3), padding="SAME", **kw)
        if cfg.pixel_features:
            # Pixel stem: 3x3 convolutions on the crop itself (configs.RefinerConfig).
            self.pixel_stem = nnx.List([nnx.Conv(3, cfg.pixel_features, **conv),
                                        nnx.Conv(cfg.pixel_features, cfg.pixel_features, **conv)])
        else:
            self.pixel_stem = nnx.data(None)
        stem_dim = 0
        if cfg.pretrained_stem in STEMS:
            # A pretrained stem (configs.RefinerConfig.pretrained_stem): its features join the patch
            # embeddings through a linear layer that starts at zero, so a fresh network
            # starts as the one without the stem.
            stem_dim = STEM_CHANNELS[cfg.pretrained_stem]
            self.stem = STEMS[cfg.pretrained_stem](rngs)
            self.stem_tokens = nnx.Linear(stem_dim, cfg.width, kernel_init=nnx.initializers.zeros,
                                          **kw)
        else:
            self.stem = self.stem_tokens = nnx.data(None)
        joined = cfg.pixel_features + stem_dim
        # What the stems give at the map's resolution joins DPT's output by a 3x3 convolution.
        self.pixel_join = nnx.Conv(head_in + joined, head_in, **conv) if joined else nnx.data(None)
        # With stem_descriptors the head is a correction to the stem's features, zero at first.
        zero = dict(kernel_init=nnx.initializers.zeros) if cfg.stem_descriptors else {}
        self.desc_head = nnx.Conv(head_in, cfg.descriptor_dim, (1, 1), **zero, **kw)
        self.mask_head = nnx.Conv(head_in, 1, (1, 1), **kw)

    def _pixel_features(self, images: Array) -> Array:
        """[N, H, W, 3] in [0, 1] -> [N, h, h, pixel_features]: the stem at the crop's
        resolution, resized to the map (bilinear, pixel centres aligned)."""
        x = images.astype(self.cfg.dtype) * 2.0 - 1.0
        for conv in self.pixel_stem:
            x = jax.nn.relu(conv(x))
        return resize(x, (self.cfg.output_size, self.cfg.output_size))

    def _check_inputs(self, real: Array, renders: Array) -> tuple[int, int, int]:
        s = self.cfg.crop_size
        if real.ndim != 5 or real.shape[2:] != (s, s, 3):
            raise ValueError(f"real crops must be [B, V, {s}, {s}, 3] (crop_size {s}), got "
                             f"{real.shape}")
        b, v = real.shape[:2]
        if renders.ndim != 6 or renders.shape[0] != b or renders.shape[2:] != (v, s, s, 3):
            raise ValueError(f"renders must be [B={b}, K, V={v}, {s}, {s}, 3] to match the real "
                             f"crops {real.shape}, got {renders.shape}")
        return b, renders.shape[1], v

    def __call__(self, real: Array, renders: Array) -> dict[str, Array]:
        cfg = self.cfg
        real, renders = jnp.asarray(real), jnp.asarray(renders)
        b, k, v = self._check_inputs(real, renders)
        s, g, h = cfg.crop_size, cfg.grid_size, cfg.output_size
        n_real, n_pair = b * v, b * k * v
        # One encoder call over the real crops (ordered b, v) and the renders (b, k, v).
        images = jnp.concatenate([unit_range(real).reshape(n_real, s, s, 3),
                                  unit_range(renders).reshape(n_pair, s, s, 3)])
        # XFeat's [N, S/8, S/8, 64], ALIKED's [N, S, S, 128].
        stem = None if self.stem is None else self.stem(images)["features"]
        offsets = None
        if stem is not None:
            offsets = self.stem_tokens(resize(stem, (g, g)).reshape(n_real + n_pair, g * g, -1))
        enc = self.encoder(images, layers=cfg.encoder_hooks[:3], patch_offsets=offsets)
        tokens = jnp.concatenate([enc["patch_tokens"], enc["register_tokens"]], axis=1)
        num_patches = enc["patch_tokens"].shape[1]

        def per_pair(x: Array) -> Array:
            """Real-crop rows [B*V, ...] -> broadcast over hypotheses [B*K*V, ...]."""
            x = jnp.broadcast_to(x.reshape(b, 1, v, *x.shape[1:]), (b, k, v, *x.shape[1:]))
            return x.reshape(n_pair, *x.shape[3:])

        # Cross-attention: real view v (queries) -> render of view v under hypothesis k.
        x, context = per_pair(tokens[:n_real]), tokens[n_real:]
        for block in self.cross_blocks:
            x = apply_cross_block(block, x, context, remat=cfg.remat)
        x = self.top_norm(x)  # [B*K*V, P + R, D]
        view_scores = self.score_head(x[:, num_patches]).astype(jnp.float32).reshape(b, k, v)

        # DPT over 2 * B*K*V maps (real per hypothesis, then renders). The real crop's levels
        # from conditioned_levels on (the finest) do not depend on the hypothesis and are
        # reassembled once; the coarser ones read the cross-attention output.
        first_cond = 4 - cfg.conditioned_levels
        render_top = self.top_norm(enc["patch_tokens"][n_real:])
        levels = []
        for i in range(4):
            if i < first_cond:
                lv = enc["layers"][i]
                real_level = per_pair(self.dpt.reassemble(i, lv[:n_real], g))
                render_tokens = lv[n_real:]
            else:
                # The render's counterpart: its last encoder block, as the cross-attention
                # output is the real crop's last block plus what it read from the render.
                real_level = self.dpt.reassemble(i, x[:, :num_patches], g)
                render_tokens = render_top
            levels.append(jnp.concatenate([real_level,
                                           self.dpt.reassemble(i, render_tokens, g)]))
        feats = self.dpt.fuse(levels)  # [2 * B*K*V, h, h, F/2]
        stem_map = None if stem is None else resize(stem, (h, h)).astype(cfg.dtype)
        if self.pixel_join is not None:
            pix = []  # at the map's resolution, real crops then renders
            if self.pixel_stem is not None:
                pix.append(self._pixel_features(images))
            if stem_map is not None:
                pix.append(stem_map)
            pix = jnp.concatenate(pix, -1)
            pix = jnp.concatenate([per_pair(pix[:n_real]), pix[n_real:]])
            feats = jax.nn.relu(self.pixel_join(jnp.concatenate([feats, pix], -1)))
        desc = self.desc_head(feats)
        if cfg.stem_descriptors:
            desc = desc + jnp.concatenate([per_pair(stem_map[:n_real]), stem_map[n_real:]])
        desc = unit_vectors(desc).reshape(2, b, k, v, h, h, cfg.descriptor_dim)
        mask_logits = self.mask_head(feats[:n_pair]).astype(jnp.float32).reshape(b, k, v, h, h)
        return {
            "real_desc": desc[0],
            "render_desc": desc[1],
            "mask_logits": mask_logits,
            "view_scores": view_scores,
            "scores": view_scores.mean(axis=-1),
        }


def _nbytes(tree: Any) -> int:
    return int(sum(math.prod(x.shape) * np.dtype(x.dtype).itemsize
                   for x in jax.tree_util.tree_leaves(tree)))


def _saved_residual_bytes(fn, params: Any, *args: Any) -> int:
    """Bytes the backward pass of ``sum(fn(params, *args))`` keeps from the forward pass.

    ``jax.vjp``'s pullback closes over exactly the residuals the backward pass needs (after
    rematerialisation); ``jax.eval_shape`` gives their shapes without computing anything.
    Residuals that are the inputs themselves (parameters, images) are not counted: they are
    held anyway.
    """
    def residuals(p, *a):
        def loss(q):
            out = fn(q, *a)
            return sum(jnp.sum(o.astype(jnp.float32)) for o in jax.tree_util.tree_leaves(out))

        _, pullback = jax.vjp(loss, p)
        inputs = jax.tree_util.tree_leaves((p, a))
        return [r for r in jax.tree_util.tree_leaves(pullback)
                if not any(r is i for i in inputs)]

    return _nbytes(jax.eval_shape(residuals, params, *args))


def memory_plan(cfg: RefinerConfig | None = None, *, instances: int = 64, hypotheses: int = 5,
                views: int = 1, devices: int = 1, fsdp: bool = True,
                adam_state_dtype: Any = jnp.float32) -> dict[str, int]:
    """Bytes per device of one training step of the refiner, from shapes only (no compute).

    Defaults: the ``paper`` size at 64 instances per batch, each with 5 jittered hypotheses
    (the classification loss's J) and 1 view. ``devices`` share the batch (data parallel);
    with ``fsdp`` the parameters, gradients and optimizer state are sharded over them too
    (mesh axes ``("data", "fsdp")`` over the same devices), else replicated. Entries:

    - ``parameters``: every ``nnx.Param`` in ``param_dtype`` (``nnx.eval_shape``).
    - ``gradients``: one gradient per parameter, same dtype.
    - ``optimizer``: Adam(W)'s two moments in ``adam_state_dtype`` (optax keeps them in the
      parameter dtype by default).
    - ``activations_saved``: the residuals the backward pass keeps from the forward pass of
      one instance shard (``jax.vjp`` under ``jax.eval_shape``, remat applied as configured:
      with ``remat`` the blocks keep only their inputs, DPT keeps everything), excluding the
      inputs themselves; a stand-in loss sums every output, so the losses' own residuals are
      not included.
    - ``activations_block``: the largest transient of the backward pass, one encoder or
      cross-attention block's residuals recomputed at once (attention logits in float32
      included), which sits on top of the saved residuals at the peak.
    - ``inputs``: the uint8 real crops and renders of the shard.
    - ``matching_logits``: what the matching loss needs if it materialises every
      (hypothesis, view) pair's [h*w, h*w] float32 logits at once (logits and softmax: x2);
      a loss that loops over pairs needs 1 / (B K V) of it. Not in ``total``.
    - ``total``: the sum of the entries above except ``matching_logits``.
    """
    cfg = get_refiner_config("paper") if cfg is None else cfg
    if min(instances, hypotheses, views, devices) < 1:
        raise ValueError("instances, hypotheses, views and devices must all be >= 1")
    per_device = -(-instances // devices)
    abstract = nnx.eval_shape(lambda: Refiner(cfg, rngs=nnx.Rngs(0)))
    graphdef, params, rest = nnx.split(abstract, nnx.Param, ...)
    param_bytes = _nbytes(params)
    shard = devices if fsdp else 1
    s = cfg.crop_size
    real = jax.ShapeDtypeStruct((per_device, views, s, s, 3), jnp.uint8)
    renders = jax.ShapeDtypeStruct((per_device, hypotheses, views, s, s, 3), jnp.uint8)

    def forward(p, r, q):
        return nnx.merge(graphdef, p, rest)(r, q)

    saved = _saved_residual_bytes(forward, params, real, renders)

    # One block's full residuals (no remat): encoder blocks see every image, cross-attention
    # blocks every (hypothesis, view) pair with the render tokens as context.
    vit = cfg.vit
    tokens = cfg.grid_size**2 + cfg.num_registers
    n_images, n_pairs = per_device * views * (hypotheses + 1), per_device * views * hypotheses
    act = jax.ShapeDtypeStruct((n_images, tokens, cfg.width), cfg.dtype)
    pair = jax.ShapeDtypeStruct((n_pairs, tokens, cfg.width), cfg.dtype)
    enc_g, enc_p = nnx.split(nnx.eval_shape(lambda: EncoderBlock(vit, rngs=nnx.Rngs(0))))
    crs_g, crs_p = nnx.split(nnx.eval_shape(lambda: CrossAttentionBlock(vit, rngs=nnx.Rngs(0))))
    block = max(
        _saved_residual_bytes(lambda p, x: nnx.merge(enc_g, p)(x), enc_p, act),
        _saved_residual_bytes(lambda p, x, c: nnx.merge(crs_g, p)(x, c), crs_p, pair, pair),
    )
    h = cfg.output_size
    plan = {
        "parameters": -(-param_bytes // shard),
        "gradients": -(-param_bytes // shard),
        "optimizer": -(-2 * count_params(abstract) * np.dtype(adam_state_dtype).itemsize
                       // shard),
        "activations_saved": saved,
        "activations_block": block,
        "inputs": _nbytes((real, renders)),
    }
    plan["total"] = sum(plan.values())
    plan["matching_logits"] = 2 * n_pairs * (h * h) ** 2 * 4
    return plan
