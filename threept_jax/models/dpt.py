"""DPT dense decoder (Ranftl, Bochkovskiy and Koltun, "Vision Transformers for Dense
Prediction", ICCV 2021), in Flax NNX.

Four token maps of a ViT (patch tokens only: registers are dropped, DPT's "ignore" readout)
are *reassembled* into an image-like pyramid: a 1x1 projection to the level's width, then a
resampling to strides patch/4 (4x4 transposed convolution, stride 4), patch/2 (2x2, stride 2),
patch (identity) and 2 patch (2x2 convolution, stride 2), then a 3x3 convolution to the common
``features`` width. *Fusion* runs from the coarsest level: each RefineNet-style block adds a
residual-convolution unit of the skip level, applies a second one, resizes to the next level's
size and mixes with a 1x1 convolution. The last block resizes to the requested output size,
and a head of two 3x3 convolutions (the second followed by ReLU) gives ``features / 2``
channels per pixel, for the caller's 1x1 output heads.

Departures from the reference code, all for pixel alignment: the coarsest level is reduced by
a 2x2 stride-2 convolution (DPT: 3x3, whose output centres sit half a patch off the half-pixel
grid); every resize is bilinear with half-pixel centres (``jax.image.resize``), not
``align_corners=True``, so pixel (i, j) of a map of side h over a crop of side H is the crop
point ((j + 0.5) H / h - 0.5, (i + 0.5) H / h - 0.5) at every level (exactly so for an even
patch grid); and the last fusion resizes straight to the output size instead of doubling, then
doubling again in the head (the reference's output is 16 x the patch grid, ours is
``output_size``, by default 4 x the grid). Shapes: N images, g patch grid side, P = g * g
patches, D token width, F fusion width, h output side.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
from flax import nnx

Array = jax.Array


def resize(x: Array, size: tuple[int, int]) -> Array:
    """[N, h0, w0, F] -> [N, h, w, F], bilinear with half-pixel centres; identity at equal size."""
    if tuple(x.shape[1:3]) == tuple(size):
        return x
    return jax.image.resize(x, (x.shape[0], *size, x.shape[-1]), method="bilinear")


class ResidualConvUnit(nnx.Module):
    """x + conv3x3(relu(conv3x3(relu(x)))) on [N, h, w, F] (DPT, without batch norm)."""

    def __init__(self, features: int, *, dtype: Any, param_dtype: Any, rngs: nnx.Rngs):
        kw = dict(kernel_size=(3, 3), padding="SAME", dtype=dtype, param_dtype=param_dtype,
                  rngs=rngs)
        self.conv1 = nnx.Conv(features, features, **kw)
        self.conv2 = nnx.Conv(features, features, **kw)

    def __call__(self, x: Array) -> Array:
        return x + self.conv2(jax.nn.relu(self.conv1(jax.nn.relu(x))))


class FusionBlock(nnx.Module):
    """DPT feature fusion: ``out_conv(resize(rcu2(x + rcu1(skip)), size))`` on [N, h, w, F].

    The coarsest block has no skip input (``with_skip=False``) and so no first unit.
    """

    def __init__(self, features: int, *, with_skip: bool, dtype: Any, param_dtype: Any,
                 rngs: nnx.Rngs):
        kw = dict(dtype=dtype, param_dtype=param_dtype, rngs=rngs)
        self.rcu1 = ResidualConvUnit(features, **kw) if with_skip else nnx.data(None)
        self.rcu2 = ResidualConvUnit(features, **kw)
        self.out_conv = nnx.Conv(features, features, kernel_size=(1, 1), **kw)

    def __call__(self, x: Array, skip: Array | None, size: tuple[int, int]) -> Array:
        if (skip is None) != (self.rcu1 is None):
            raise ValueError("a DPT fusion block takes a skip level exactly when built with one")
        if skip is not None:
            x = x + self.rcu1(skip)
        return self.out_conv(resize(self.rcu2(x), size))


def _fuse_block(block: FusionBlock, x: Array, skip: Array | None, size: tuple[int, int]) -> Array:
    return block(x, skip, size)


def _head(dpt: DPT, x: Array) -> Array:
    return jax.nn.relu(dpt.head2(dpt.head1(x)))


_fuse_block_remat = nnx.remat(_fuse_block, static_argnums=(3,))
_head_remat = nnx.remat(_head)


class DPT(nnx.Module):
    """DPT decoder: four token maps [N, P, D] on a g x g grid -> features [N, h, h, F/2].

    ``dims`` are the reassembled widths of the four levels (strides patch/4, patch/2, patch,
    2 patch), ``features`` the fusion width F, ``output_size`` h. :meth:`reassemble` and
    :meth:`fuse` are separate so a caller can reassemble a level once and share it (the
    refiner shares the real crop's first three levels across hypotheses); ``__call__`` runs
    both. With ``remat`` each fusion block and the head are rematerialised in the backward
    pass (at output maps of 64 x 64 x 256 they hold most of a training step's activations).
    """

    def __init__(self, width: int, dims: Sequence[int], features: int, output_size: int, *,
                 remat: bool = False, dtype: Any, param_dtype: Any, rngs: nnx.Rngs):
        if len(dims) != 4:
            raise ValueError(f"DPT needs four level widths, got {dims}")
        self.output_size = int(output_size)
        self.remat = bool(remat)
        kw = dict(dtype=dtype, param_dtype=param_dtype, rngs=rngs)
        self.project = nnx.List([nnx.Conv(width, d, kernel_size=(1, 1), **kw) for d in dims])
        self.resample = nnx.List([
            nnx.ConvTranspose(dims[0], dims[0], (4, 4), (4, 4), padding="VALID", **kw),
            nnx.ConvTranspose(dims[1], dims[1], (2, 2), (2, 2), padding="VALID", **kw),
            nnx.data(None),
            nnx.Conv(dims[3], dims[3], (2, 2), (2, 2), padding="SAME", **kw),
        ])
        self.layer_rn = nnx.List([nnx.Conv(d, features, (3, 3), padding="SAME", use_bias=False,
                                           **kw) for d in dims])
        self.fusion = nnx.List([FusionBlock(features, with_skip=i < 3, **kw) for i in range(4)])
        self.head1 = nnx.Conv(features, features // 2, (3, 3), padding="SAME", **kw)
        self.head2 = nnx.Conv(features // 2, features // 2, (3, 3), padding="SAME", **kw)

    def reassemble(self, level: int, tokens: Array, grid: int) -> Array:
        """Level ``level`` (0..3): tokens [N, g*g, D] -> [N, s, s, F] with s = 4g, 2g, g,
        ceil(g / 2)."""
        n, p, d = tokens.shape
        if p != grid * grid:
            raise ValueError(f"DPT level {level} has {p} tokens, a {grid}x{grid} grid needs "
                             f"{grid * grid} (pass patch tokens only, without registers)")
        x = self.project[level](tokens.reshape(n, grid, grid, d))
        if self.resample[level] is not None:
            x = self.resample[level](x)
        return self.layer_rn[level](x)

    def fuse(self, levels: Sequence[Array]) -> Array:
        """Four reassembled levels (finest first) -> [N, h, h, F/2] (ReLU'd head features)."""
        l0, l1, l2, l3 = levels
        fuse, head = (_fuse_block_remat, _head_remat) if self.remat else (_fuse_block, _head)
        x = fuse(self.fusion[3], l3, None, tuple(l2.shape[1:3]))
        x = fuse(self.fusion[2], x, l2, tuple(l1.shape[1:3]))
        x = fuse(self.fusion[1], x, l1, tuple(l0.shape[1:3]))
        x = fuse(self.fusion[0], x, l0, (self.output_size, self.output_size))
        return head(self, x)

    def __call__(self, tokens: Sequence[Array], grid: int) -> Array:
        """Four token maps [N, g*g, D] (shallow to deep) -> [N, h, h, F/2]."""
        return self.fuse([self.reassemble(i, t, grid) for i, t in enumerate(tokens)])
