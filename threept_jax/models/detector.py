"""3PT-D: the early-fusion CAD-conditioned detector (docs/design.md section 1.1).

Separately callable (and separately jit-able) stages:

1. ``embed_object(prior_renders [O, V, h, w, 3]) -> prior_tokens [O, Np, D]``: the object
   tower encodes the V = 12 prior renders of each object; each view's patch tokens are reduced
   to ``tokens_per_view`` tokens by attention pooling and projected into the image tower's
   input space; views are concatenated (Np = V * tokens_per_view). Computed once per object
   and cached.
2. ``embed_templates(template_renders [O, T, h, w, 3]) -> template_bank [O, T, E]``: one unit
   vector per template rotation (attention pooling with one probe, projection to E,
   L2 normalisation). Computed once per object (T = 1024 by default at inference, the
   paper's 5140 on request) and cached.
3. ``detect(image_tiles [B, H, W, 3], prior_tokens [B, Np, D])``: the prior tokens, tagged
   with a learned per-slot embedding, are concatenated to the tile's patch tokens and the
   image tower attends over all of them (early fusion). Every output patch token is an object
   hypothesis with an amodal box (sigmoid of MLP + grid prior, OWL-ViT, stretched past the
   tile: ``heads.decode_boxes``), a presence logit and a unit
   embedding [B, P, E].
4. ``orientation_scores(embeddings, template_bank) -> [B, P, T]``: cosine similarities, one
   matrix multiply. Orientation logits are ``scale * cos + bias`` with a learned scalar scale
   and bias (OWL-ViT/SigLIP-style logit scale and shift); the detection logit of a hypothesis
   is the maximum over templates.

The towers share one ViT by default (see :class:`DetectorConfig`). Heads start neutral: box
and presence MLPs have zero-initialised output kernels, so every patch starts by proposing its
own cell with presence probability ``class_prior`` (0.01), and the orientation logits start at
``logit(class_prior) + scale * (cos - 1)``, i.e. never above the same prior.

Shapes: O objects, V prior views, T templates, B tiles, H W tile size, h w render size,
P patches, Np prior tokens, D backbone width, E embedding dim. Boxes are normalised cxcywh
(x divided by tile width, y by tile height); pixel boxes are xyxy in pixel-edge coordinates.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from threept_jax.geometry.boxes import cxcywh_to_xyxy
from threept_jax.models.configs import DetectorConfig
from threept_jax.models.heads import (
    AttentionPool,
    PredictorMLP,
    decode_boxes,
    logit,
    unit_vectors,
)
from threept_jax.models.vit import ViT

Array = jax.Array


def orientation_scores(embeddings: Array, template_bank: Array) -> Array:
    """Cosine similarities [B, P, T] of hypotheses [B, P, E] with templates [B, T, E] or [T, E].

    Embeddings are re-normalised (cheap); the template bank must already hold unit vectors,
    as ``Detector.embed_templates`` returns them. One einsum over E.
    """
    e = unit_vectors(embeddings)
    bank = jnp.asarray(template_bank, jnp.float32)
    if bank.ndim == 2:
        return jnp.einsum("bpe,te->bpt", e, bank)
    if bank.ndim != 3 or bank.shape[0] != e.shape[0]:
        raise ValueError(
            f"template_bank must be [T, E] or [B={e.shape[0]}, T, E], got {bank.shape}; pass the "
            "bank of the object queried in each tile (index the cached [O, T, E] bank)"
        )
    return jnp.einsum("bpe,bte->bpt", e, bank)


def orientation_logits(embeddings: Array, template_bank: Array, logit_scale: Array,
                       logit_bias: Array) -> Array:
    """[B, P, T] ``scale * cos + bias``; ``logit_scale`` is the (positive) scale itself."""
    return logit_scale * orientation_scores(embeddings, template_bank) + logit_bias


def boxes_to_pixels(boxes: Array, image_hw: tuple[int, int]) -> Array:
    """Normalised cxcywh [..., 4] -> xyxy [..., 4] in pixel-edge coordinates of an H x W image."""
    h, w = image_hw
    scale = jnp.asarray([w, h, w, h], jnp.float32)
    return cxcywh_to_xyxy(boxes) * scale


#: What :func:`detection_scores` can rank patches by. The default, used by inference and by the
#: training evaluation's headline (``eval/ap50``), is the mode that measured best on full
#: held-out images over the 21 evaluations of issue 13's CPU runs (docs/training.md, "CPU
#: recipes"): mean AP50 template 0.0045, presence 0.0031, product 0.0018; template also led the
#: longest run, zero-shot on held-out parts (0.0063 / 0.0021 / 0.0017 over 13 evaluations). It
#: is the paper's score. At these levels the evidence is weak: revisit it with a detector
#: trained at scale (``eval/ap50_<mode>`` logs all three).
SCORE_MODES = ("product", "presence", "template")
DEFAULT_SCORE_MODE = "template"


def detection_scores(presence_logit: Array, detection_logit: Array | None, mode: str) -> Array:
    """Per-hypothesis detection score in [0, 1] from the presence logits [..., P] and the best
    template logits [..., P] (``Detector.__call__``'s ``detection_logits``, the maximum over
    the template bank).

    ``"template"``: ``sigmoid(best template logit)``, the paper's detection score (the maximum
    similarity over all orientation templates, section 3.1); ``"presence"``:
    ``sigmoid(presence)`` (``detection_logit`` may be None); ``"product"``: the two multiplied.
    The loss trains the template logits of every hypothesis
    (:mod:`threept_jax.losses.detection`), so each mode is a score of its own.
    """
    if mode not in SCORE_MODES:
        raise ValueError(f"unknown detection score mode {mode!r}; use one of {SCORE_MODES}")
    presence = jax.nn.sigmoid(jnp.asarray(presence_logit, jnp.float32))
    if mode == "presence":
        return presence
    if detection_logit is None:
        raise ValueError(f"detection score mode {mode!r} needs the best template logits "
                         "[..., P]; pass them, or use mode='presence'")
    detection_logit = jnp.asarray(detection_logit, jnp.float32)
    if detection_logit.shape != presence.shape:
        raise ValueError(f"detection_logit must have the presence logits' shape "
                         f"{presence.shape}, got {detection_logit.shape}")
    template = jax.nn.sigmoid(detection_logit)
    return template if mode == "template" else presence * template


class Detector(nnx.Module):
    """3PT-D (see the module docstring for the stages and shapes)."""

    def __init__(self, cfg: DetectorConfig, *, rngs: nnx.Rngs):
        self.cfg = cfg
        vit = cfg.vit
        kw = dict(dtype=cfg.dtype, param_dtype=cfg.param_dtype, rngs=rngs)
        dense = dict(kernel_init=nnx.initializers.xavier_uniform(), **kw)
        d = cfg.width
        self.image_tower = ViT(vit, rngs=rngs)
        # Sharing is by reference: NNX stores the module once and both towers train it.
        self.object_tower = self.image_tower if cfg.share_backbone else ViT(vit, rngs=rngs)
        self.prior_pool = AttentionPool(d, cfg.tokens_per_view, vit.num_heads, vit.mlp_dim, **kw)
        self.prior_proj = nnx.Linear(d, d, **dense)
        self.prior_slot_embed = nnx.Param(
            nnx.initializers.normal(0.02)(rngs.params(), (cfg.num_prior_tokens, d),
                                          cfg.param_dtype))
        self.template_pool = AttentionPool(d, 1, vit.num_heads, vit.mlp_dim, **kw)
        self.template_proj = nnx.Linear(d, cfg.embed_dim, **dense)
        self.embed_head = nnx.Linear(d, cfg.embed_dim, **dense)
        self.box_head = PredictorMLP(d, 4, num_layers=cfg.box_head_layers, **kw)
        self.presence_head = PredictorMLP(
            d, 1, num_layers=cfg.presence_head_layers,
            out_bias=logit(cfg.class_prior), **kw)
        # The scale is stored as its log so that it stays positive; the bias starts so that a
        # perfect match (cos = 1) gives exactly the class prior (focal-loss prior init).
        self.log_logit_scale = nnx.Param(
            jnp.asarray(np.log(cfg.logit_scale_init), cfg.param_dtype))
        self.logit_bias = nnx.Param(
            jnp.asarray(logit(cfg.class_prior) - cfg.logit_scale_init, cfg.param_dtype))

    # -- object tower ---------------------------------------------------------------------

    def _check_renders(self, renders: Array, name: str) -> None:
        if renders.ndim != 5 or renders.shape[-1] != 3:
            raise ValueError(f"{name} must be [O, N, h, w, 3], got shape {renders.shape}")
        h, w = renders.shape[2:4]
        if (h, w) != (self.cfg.render_size,) * 2:
            raise ValueError(
                f"{name} are {h}x{w} but the detector was configured with render_size="
                f"{self.cfg.render_size}; render at that size or change DetectorConfig.render_size"
            )

    def embed_object(self, prior_renders: Array) -> Array:
        """Prior renders [O, V, h, w, 3] -> prior tokens [O, V * tokens_per_view, D] (float32)."""
        self._check_renders(prior_renders, "prior_renders")
        o, v = prior_renders.shape[:2]
        if v != self.cfg.num_prior_views:
            raise ValueError(
                f"expected {self.cfg.num_prior_views} prior views per object, got {v} "
                "(render the views of geometry.grids.prior_view_rotations())"
            )
        x = prior_renders.reshape(o * v, *prior_renders.shape[2:])
        tokens = self.object_tower(x)["patch_tokens"]
        pooled = self.prior_proj(self.prior_pool(tokens))  # [O*V, k, D]
        return pooled.reshape(o, v * self.cfg.tokens_per_view, -1).astype(jnp.float32)

    def _template_embeddings(self, renders: Array) -> Array:
        tokens = self.object_tower(renders)["patch_tokens"]
        return unit_vectors(self.template_proj(self.template_pool(tokens)[:, 0]))

    def embed_templates(self, template_renders: Array, chunk_size: int | None = None) -> Array:
        """Template renders [O, T, h, w, 3] -> unit template bank [O, T, E] (float32).

        ``chunk_size`` bounds memory: renders are encoded ``chunk_size`` at a time in a
        ``lax.map`` (one compiled body), which the 5140-template onboarding needs.
        """
        self._check_renders(template_renders, "template_renders")
        o, t = template_renders.shape[:2]
        x = template_renders.reshape(o * t, *template_renders.shape[2:])
        n = o * t
        if chunk_size is None or chunk_size >= n:
            bank = self._template_embeddings(x)
        else:
            if chunk_size < 1:
                raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
            num_chunks = -(-n // chunk_size)
            pad = num_chunks * chunk_size - n
            x = jnp.concatenate([x, jnp.zeros((pad, *x.shape[1:]), x.dtype)]) if pad else x
            bank = jax.lax.map(self._template_embeddings,
                               x.reshape(num_chunks, chunk_size, *x.shape[1:]))
            bank = bank.reshape(num_chunks * chunk_size, -1)[:n]
        return bank.reshape(o, t, -1)

    # -- image tower ----------------------------------------------------------------------

    @property
    def logit_scale(self) -> Array:
        """Positive scalar scale of the orientation logits."""
        return jnp.exp(self.log_logit_scale[...].astype(jnp.float32))

    def detect(self, image_tiles: Array, prior_tokens: Array,
               prior_mask: Array | None = None) -> dict[str, Array]:
        """Early-fusion detection on tiles [B, H, W, 3] with prior tokens [B, Np, D].

        Returns ``boxes`` [B, P, 4] (normalised cxcywh), ``presence_logits`` [B, P] and unit
        ``embeddings`` [B, P, E], all float32. ``prior_mask`` [B, Np] (True = real token)
        hides padded prior tokens.
        """
        cfg = self.cfg
        if image_tiles.ndim != 4:
            raise ValueError(f"image_tiles must be [B, H, W, 3], got shape {image_tiles.shape}")
        b = image_tiles.shape[0]
        expected = (b, cfg.num_prior_tokens, cfg.width)
        if tuple(prior_tokens.shape) != expected:
            raise ValueError(
                f"prior_tokens must be [B, Np, D] = {expected}, got {tuple(prior_tokens.shape)}; "
                "compute them with embed_object and index the object queried in each tile"
            )
        grid = self.image_tower.grid(image_tiles.shape[1:3])
        prior = prior_tokens.astype(cfg.dtype) + self.prior_slot_embed[...].astype(cfg.dtype)[None]
        x = self.image_tower(image_tiles, prior, prior_mask)["patch_tokens"]
        boxes = decode_boxes(self.box_head(x), *grid)
        return {
            "boxes": boxes,
            "presence_logits": self.presence_head(x)[..., 0],
            "embeddings": unit_vectors(self.embed_head(x)),
        }

    def orientation_logits(self, embeddings: Array, template_bank: Array) -> Array:
        """[B, P, T] learned-scale-and-bias logits of hypotheses against templates."""
        return orientation_logits(embeddings, template_bank, self.logit_scale,
                                  self.logit_bias[...].astype(jnp.float32))

    def __call__(self, image_tiles: Array, prior_tokens: Array, template_bank: Array | None = None,
                 prior_mask: Array | None = None) -> dict[str, Array]:
        """``detect`` plus, given ``template_bank`` [B, T, E] (or [T, E]), what the loss needs.

        Adds ``template_bank``, ``logit_scale`` and ``logit_bias`` (scalars) and
        ``detection_logits`` [B, P] = max over templates of the orientation logits.
        """
        out = self.detect(image_tiles, prior_tokens, prior_mask)
        if template_bank is not None:
            scale = self.logit_scale
            bias = self.logit_bias[...].astype(jnp.float32)
            out["template_bank"] = jnp.asarray(template_bank, jnp.float32)
            out["logit_scale"] = scale
            out["logit_bias"] = bias
            # max_t(s * cos + b) = s * max_t(cos) + b because s > 0.
            out["detection_logits"] = (
                scale * jnp.max(orientation_scores(out["embeddings"], template_bank), -1) + bias)
        return out
