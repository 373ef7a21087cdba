"""Sigmoid focal loss (Lin et al., "Focal Loss for Dense Object Detection", ICCV 2017).

Element-wise, for a logit x with p = sigmoid(x) and a target t in [0, 1]:

    FL(x, t) = t * alpha * (1 - p)^gamma * (-log p)
             + (1 - t) * w_neg * (1 - alpha) * p^gamma * (-log(1 - p))

with ``alpha=None`` meaning no class balancing (both alpha factors are 1) and ``w_neg`` an
optional per-element weight on the negative term (used by the soft-scaled matching loss).
-log p and -log(1 - p) are computed as softplus(-x) and softplus(x), which stay finite for
any logit.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

Array = jax.Array


def _alphas(alpha: float | None) -> tuple[float, float]:
    if alpha is None:
        return 1.0, 1.0
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"focal alpha must be in [0, 1] or None, got {alpha}")
    return alpha, 1.0 - alpha


def sigmoid_focal_loss(logits: Array, targets: Array, *, alpha: float | None = 0.25,
                       gamma: float = 2.0, negative_weight: Array | None = None) -> Array:
    """Element-wise focal loss, same shape as ``logits`` (broadcast with ``targets``)."""
    x = jnp.asarray(logits, jnp.float32)
    t = jnp.asarray(targets, jnp.float32)
    a_pos, a_neg = _alphas(alpha)
    p = jax.nn.sigmoid(x)
    pos = a_pos * (1.0 - p) ** gamma * jax.nn.softplus(-x)
    neg = a_neg * p**gamma * jax.nn.softplus(x)
    if negative_weight is not None:
        neg = neg * jnp.asarray(negative_weight, jnp.float32)
    return t * pos + (1.0 - t) * neg


def focal_matching_cost(logits: Array, *, alpha: float | None = 0.25, gamma: float = 2.0) -> Array:
    """Classification cost of assigning a target to each prediction, same shape as ``logits``.

    The focal loss of the prediction as a positive minus its focal loss as a negative
    (Deformable-DETR / scenic ``sigmoid_cost``): what matching it changes in the loss.
    """
    x = jnp.asarray(logits, jnp.float32)
    a_pos, a_neg = _alphas(alpha)
    p = jax.nn.sigmoid(x)
    pos = a_pos * (1.0 - p) ** gamma * jax.nn.softplus(-x)
    neg = a_neg * p**gamma * jax.nn.softplus(x)
    return pos - neg
