"""The templates detector's learned verifier: is this candidate the part it claims to be?

The training-free detector (``infer.shape_detect``) scores each verified candidate by a
logistic model of eight outline features (``threept_jax.pipeline.shape_search``); what they
cannot see is inside the outline: a washer's hole, a bracket's fold, the shading of a turned
face. :class:`CandidateVerifier` looks at the image around the candidate beside the part
rendered at the candidate's pose (its silhouette, its geometric edges, its shading) and adds
a correction to the logistic model's log-odds, so a verifier that learned nothing (its last
layer at zero, as it starts) leaves the score as it was.

Inputs, one row per candidate (``pipeline.shape_search.verifier_inputs`` makes them):

* ``crops`` [N, S, S, 3] uint8: the image in a square box around the candidate's outline;
* ``renders`` [N, S, S, 3] uint8: the part rendered at the candidate's pose into the same box
  (channels: silhouette, geometric edges, |normal z| inside the silhouette, 0-255);
* ``inputs`` [N, F] float: the logistic model's inputs (``score_inputs``), standardised here
  by the training data's mean and spread (stored in the module, not trained).

It is trained by ``python -m train.templates_verifier`` on candidates of procedural parts and
BOP meshes in path-traced cells, with random materials, never on the parts it is evaluated on;
``models/templates-verifier/`` ships the weights with their card.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import nnx

Array = jax.Array

#: Side (px) of the crops and renders the verifier reads.
CROP = 64


class Standardization(nnx.Variable):
    """A constant of the data (the score inputs' mean or spread): stored, not trained."""


class CandidateVerifier(nnx.Module):
    """Five stride-2 convolutions (GroupNorm, GELU) over the crop and render stacked, their
    mean and max pooled, with the standardised score inputs into a 64-unit hidden layer and a
    zero-initialised output: the correction to the score's log-odds [N] (module docstring)."""

    def __init__(self, *, width: int = 16, num_inputs: int = 8, rngs: nnx.Rngs):
        chans = (6, width, 2 * width, 4 * width, 4 * width, 8 * width)
        self.convs = nnx.List([nnx.Conv(chans[i], chans[i + 1], (3, 3), strides=2, rngs=rngs)
                               for i in range(5)])
        self.norms = nnx.List([nnx.GroupNorm(chans[i + 1], num_groups=8, rngs=rngs)
                               for i in range(5)])
        self.mean = Standardization(jnp.zeros(num_inputs, jnp.float32))
        self.std = Standardization(jnp.ones(num_inputs, jnp.float32))
        self.hidden = nnx.Linear(2 * chans[-1] + num_inputs, 64, rngs=rngs)
        self.out = nnx.Linear(64, 1, kernel_init=nnx.initializers.zeros, rngs=rngs)

    def __call__(self, crops: Array, renders: Array, inputs: Array,
                 dropout: Array | None = None, rate: float = 0.3) -> Array:
        """Correction to the log-odds [N]; ``dropout``: a PRNG key (training) drops the
        hidden layer's inputs at ``rate``."""
        im = crops.astype(jnp.float32)
        # Each crop to zero mean and unit spread: the materials are random, the shapes not.
        im = (im - im.mean((1, 2, 3), keepdims=True)) / (im.std((1, 2, 3), keepdims=True) + 8.0)
        h = jnp.concatenate([im, renders.astype(jnp.float32) / 255.0], -1)
        for conv, norm in zip(self.convs, self.norms):
            h = jax.nn.gelu(norm(conv(h)))
        x = (inputs.astype(jnp.float32) - self.mean[...]) / self.std[...]
        h = jnp.concatenate([h.mean((1, 2)), h.max((1, 2)), x], -1)
        if dropout is not None:
            keep = jax.random.bernoulli(dropout, 1.0 - rate, h.shape)
            h = jnp.where(keep, h / (1.0 - rate), 0.0)
        return self.out(jax.nn.gelu(self.hidden(h)))[:, 0]
