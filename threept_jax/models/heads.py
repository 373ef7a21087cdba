"""Small heads of 3PT-D (attention pooling, prediction MLPs, the OWL-ViT box grid prior) and
what the networks share: ``unit_vectors``, the one normalisation of descriptors and embeddings.

The box head follows OWL-ViT (Minderer et al., ECCV 2022; scenic ``owl_vit/models.py``
``box_predictor`` and ``utils.compute_box_bias``): each patch token predicts a box as
``sigmoid(MLP(token) + bias)`` where the bias is the inverse sigmoid of the patch's own centre
and of one patch's size, so a zero-initialised MLP starts with every patch proposing itself.
Scenic's bias uses each patch's bottom-right *corner*; we use its centre, which is where a
patch's own box is centred. Boxes are *amodal* (issue 13 item 1.4: an object cut by the tile
border keeps its whole box, which object generation reads as the object's size), so the
sigmoid is stretched to ``BOX_RANGE``: centres in (-0.5, 1.5) and sizes in (0, 2) tile sides
(:func:`decode_boxes`). Shapes: B batch, N tokens, K probes, P patches, D width.
"""

from __future__ import annotations

import itertools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from threept_jax.models.vit import Attention, LayerNorm, Mlp

Array = jax.Array


def unit_range(images: Array) -> Array:
    """Images, uint8 or float in [0, 1] -> float32 in [0, 1] (3PT-R's crops and renders; the
    ViT maps them to [-1, 1], ALIKED reads them as they are)."""
    images = jnp.asarray(images)
    if images.dtype == jnp.uint8:
        return images.astype(jnp.float32) / 255.0
    return images.astype(jnp.float32)


def matched_directly(f: Array, b: int, k: int, v: int) -> dict[str, Array]:
    """3PT-R's output contract from a pretrained network's descriptor maps alone, untrained
    (``XFeatDescriptors``, ``ALIKEDDescriptors``): ``f`` [B V + B K V, h, h, C], the real
    crops' (ordered b, v) then the renders' (b, k, v) -> ``real_desc`` (repeated over the K
    hypotheses) and ``render_desc`` [B, K, V, h, h, C], and zeros for what it has no opinion
    on: ``mask_logits`` [B, K, V, h, h], ``view_scores`` [B, K, V], ``scores`` [B, K]."""
    h, c = f.shape[1], f.shape[-1]
    real_desc = jnp.broadcast_to(f[:b * v].reshape(b, 1, v, h, h, c), (b, k, v, h, h, c))
    return {"real_desc": real_desc,
            "render_desc": f[b * v:].reshape(b, k, v, h, h, c),
            "mask_logits": jnp.zeros((b, k, v, h, h), jnp.float32),
            "view_scores": jnp.zeros((b, k, v), jnp.float32),
            "scores": jnp.zeros((b, k), jnp.float32)}


def unit_vectors(x: Array, eps: float = 1e-6) -> Array:
    """x / max(|x|, eps) along the last axis, float32: descriptors and embeddings. Through the
    squared norm (rsqrt), so the gradient stays finite at x = 0 (``jnp.linalg.norm``'s is NaN
    there, and a zero vector occurs: zero features under a zero-initialised head bias)."""
    x = x.astype(jnp.float32)
    return x * jax.lax.rsqrt(jnp.maximum(jnp.sum(x * x, axis=-1, keepdims=True), eps * eps))


def logit(p: float) -> float:
    """Inverse sigmoid of a Python probability, log(p / (1 - p)), as a Python float."""
    return float(np.log(p) - np.log1p(-p))


#: (low, high) of the decoded normalised (cx, cy, w, h): amodal boxes may pass the tile.
BOX_RANGE = (np.array([-0.5, -0.5, 0.0, 0.0]), np.array([1.5, 1.5, 2.0, 2.0]))


def decode_boxes(raw: Array, grid_h: int, grid_w: int) -> Array:
    """[..., gh * gw, 4] head outputs -> normalised cxcywh boxes ``low + (high - low) *
    sigmoid(raw + box_grid_bias)`` (``BOX_RANGE``); raw = 0 gives each patch's own cell."""
    low, high = (jnp.asarray(v, jnp.float32) for v in BOX_RANGE)
    return low + (high - low) * jax.nn.sigmoid(raw.astype(jnp.float32)
                                               + box_grid_bias(grid_h, grid_w))


def box_grid_bias(grid_h: int, grid_w: int) -> Array:
    """[gh * gw, 4] inverse-sigmoid box prior (cx, cy, w, h) of each patch, row-major.

    Patch (i, j) gets centre ((j + 0.5) / gw, (i + 0.5) / gh) and size (1 / gw, 1 / gh) in
    normalised image coordinates; the bias is the logit of those numbers mapped from
    ``BOX_RANGE`` to (0, 1), so :func:`decode_boxes` of 0 is the patch's cell.
    """
    y, x = np.mgrid[:grid_h, :grid_w].astype(np.float64)
    cx = (x.reshape(-1) + 0.5) / grid_w
    cy = (y.reshape(-1) + 0.5) / grid_h
    w = np.full_like(cx, 1.0 / grid_w)
    h = np.full_like(cy, 1.0 / grid_h)
    low, high = BOX_RANGE
    prior = (np.stack([cx, cy, w, h], -1) - low) / (high - low)
    return jnp.asarray(np.log(prior) - np.log1p(-prior), jnp.float32)


class PredictorMLP(nnx.Module):
    """[..., D] -> [..., out_dim]: ``num_layers`` Linear layers with GELU in between.

    The last layer's kernel is zero and its bias is ``out_bias`` (OWL-ViT ``PredictorMLP``),
    so at initialisation the output is exactly ``out_bias`` whatever the input.
    """

    def __init__(self, in_dim: int, out_dim: int, *, num_layers: int, hidden_dim: int | None = None,
                 out_bias: float = 0.0, dtype: Any, param_dtype: Any, rngs: nnx.Rngs):
        hidden_dim = hidden_dim or in_dim
        dims = [in_dim] + [hidden_dim] * (num_layers - 1)
        self.hidden = nnx.List([
            nnx.Linear(a, b, dtype=dtype, param_dtype=param_dtype,
                       kernel_init=nnx.initializers.xavier_uniform(), rngs=rngs)
            for a, b in itertools.pairwise(dims)
        ])
        self.out = nnx.Linear(
            dims[-1], out_dim, dtype=dtype, param_dtype=param_dtype,
            kernel_init=nnx.initializers.zeros,
            bias_init=nnx.initializers.constant(out_bias), rngs=rngs,
        )

    def __call__(self, x: Array) -> Array:
        for layer in self.hidden:
            x = jax.nn.gelu(layer(x))
        return self.out(x).astype(jnp.float32)


class AttentionPool(nnx.Module):
    """Multi-head attention pooling (MAP, big_vision ``MAPHead``): [B, N, D] -> [B, K, D].

    K learned probe tokens cross-attend to the N input tokens; the result goes through a
    LayerNorm and a residual MLP. ``mask`` [B, N] hides padded input tokens.
    """

    def __init__(self, width: int, num_probes: int, num_heads: int, mlp_dim: int, *,
                 dtype: Any, param_dtype: Any, rngs: nnx.Rngs):
        self.dtype = dtype
        init = nnx.initializers.xavier_uniform()
        self.probes = nnx.Param(init(rngs.params(), (num_probes, width), param_dtype))
        kw = dict(dtype=dtype, param_dtype=param_dtype, rngs=rngs)
        self.attn = Attention(width, num_heads, **kw)
        self.norm = LayerNorm(width, **kw)
        self.mlp = Mlp(width, mlp_dim, **kw)

    def __call__(self, x: Array, mask: Array | None = None) -> Array:
        b = x.shape[0]
        probes = jnp.broadcast_to(self.probes[...].astype(self.dtype)[None],
                                  (b, *self.probes.shape))
        y = self.attn(probes, context=x.astype(self.dtype), mask=mask)
        return y + self.mlp(self.norm(y))
