"""Vision Transformer backbone in Flax NNX (Dosovitskiy et al., ICLR 2021).

A pre-LayerNorm encoder without class token, in the manner of big_vision's ``vit.py``: sizes
come from a table parsed from strings such as ``"B/16"`` (:mod:`threept_jax.models.configs`),
optional register tokens (Darcet et al. 2024), learned position embeddings resized bilinearly
to any patch grid or fixed 2-D sin-cos ones, and attention that accepts extra tokens: 3PT-D
concatenates the object's prior tokens to the image patch tokens (early fusion, docs/design.md
section 1.1) and every token attends to every other. Optional LayerScale (DINOv2; off by
default, so the detector's parameters and numerics are those of the plain block), intermediate
block outputs for dense heads, and a CroCo cross-attention block for the refiner (3PT-R).

Every layer takes ``dtype`` (compute) and ``param_dtype`` (storage). Layer norms, the softmax
of attention and position-embedding resizing run in float32; the residual stream is kept in
``dtype``. Images enter as ``[B, H, W, 3]`` RGB, float in [0, 1] or uint8, and are mapped to
[-1, 1] inside the model. Shapes: B batch, N tokens, P patches, E extra tokens, R registers,
D width.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from threept_jax.models.configs import ViTConfig

Array = jax.Array

_dense_init = nnx.initializers.xavier_uniform()


def posemb_sincos_2d(grid_h: int, grid_w: int, width: int, temperature: float = 10_000.0) -> Array:
    """Fixed 2-D sin-cos position embedding [grid_h * grid_w, width] (row-major patches).

    MoCo v3 / big_vision ``posemb_sincos_2d``: a quarter of the channels each for sin(x),
    cos(x), sin(y), cos(y) at geometrically spaced frequencies. Dot products between two
    positions depend only on their offset.
    """
    if width % 4:
        raise ValueError(f"sincos2d position embeddings need width % 4 == 0, got {width}")
    y, x = np.mgrid[:grid_h, :grid_w].astype(np.float32)
    omega = np.arange(width // 4, dtype=np.float32) / max(width // 4 - 1, 1)
    omega = 1.0 / temperature**omega
    y = y.reshape(-1)[:, None] * omega[None]
    x = x.reshape(-1)[:, None] * omega[None]
    return jnp.asarray(np.concatenate([np.sin(x), np.cos(x), np.sin(y), np.cos(y)], axis=1))


def resize_posemb(posemb: Array, old_grid: tuple[int, int], new_grid: tuple[int, int]) -> Array:
    """Bilinear resize of a position embedding: [Gh*Gw, D] on ``old_grid`` -> [gh*gw, D].

    Half-pixel-centre bilinear interpolation (``jax.image.resize``, antialiased when shrinking),
    as scenic's ``resize_posemb`` does with ``scipy.ndimage.zoom``. At the native grid the
    embedding is returned unchanged, so a learned embedding is exact there. Runs in float32.
    """
    old_grid, new_grid = tuple(old_grid), tuple(new_grid)
    n, d = posemb.shape
    if n != old_grid[0] * old_grid[1]:
        raise ValueError(f"position embedding has {n} rows, grid {old_grid} needs "
                         f"{old_grid[0] * old_grid[1]}")
    if old_grid == new_grid:
        return posemb
    grid = posemb.astype(jnp.float32).reshape(*old_grid, d)
    grid = jax.image.resize(grid, (*new_grid, d), method="bilinear", antialias=True)
    return grid.reshape(new_grid[0] * new_grid[1], d).astype(posemb.dtype)


def to_model_range(images: Array, dtype: Any) -> Array:
    """[..., H, W, 3] uint8 or float in [0, 1] -> float in [-1, 1] of ``dtype``."""
    images = jnp.asarray(images)
    if images.shape[-1] != 3:
        raise ValueError(f"images must be [..., H, W, 3] RGB, got shape {images.shape}")
    if images.dtype == jnp.uint8:
        images = images.astype(jnp.float32) / 255.0
    return (images.astype(jnp.float32) * 2.0 - 1.0).astype(dtype)


class LayerNorm(nnx.Module):
    """LayerNorm computed in float32 whatever the compute dtype; returns ``dtype``."""

    def __init__(self, width: int, *, epsilon: float = 1e-6, dtype: Any, param_dtype: Any,
                 rngs: nnx.Rngs):
        self.dtype = dtype
        self.norm = nnx.LayerNorm(width, epsilon=epsilon, dtype=jnp.float32,
                                  param_dtype=param_dtype, rngs=rngs)

    def __call__(self, x: Array) -> Array:
        return self.norm(x.astype(jnp.float32)).astype(self.dtype)


class Mlp(nnx.Module):
    """Transformer MLP block: [..., D] -> Linear(mlp_dim) -> GELU -> Linear(out_dim or D)."""

    def __init__(self, width: int, mlp_dim: int, out_dim: int | None = None, *, dtype: Any,
                 param_dtype: Any, rngs: nnx.Rngs):
        kw = dict(dtype=dtype, param_dtype=param_dtype, kernel_init=_dense_init,
                  bias_init=nnx.initializers.normal(1e-6), rngs=rngs)
        self.fc1 = nnx.Linear(width, mlp_dim, **kw)
        self.fc2 = nnx.Linear(mlp_dim, out_dim or width, **kw)

    def __call__(self, x: Array) -> Array:
        return self.fc2(jax.nn.gelu(self.fc1(x)))


def attention_xla(q: Array, k: Array, v: Array, mask: Array | None = None) -> Array:
    """softmax(q k^T / sqrt(Dh)) v per head: q [B, N, H, Dh], k, v [B, S, H, Dh] -> [B, N, H, Dh].

    The XLA path on every backend. Heads are moved in front before the two batched matmuls, so
    both are plain [N, Dh] x [Dh, S] products per head; ``jax.nn.dot_product_attention``'s XLA
    path contracts the [B, N, H, Dh] layout directly and ran at 0.6x this speed on CPU
    (``bench/detect.py``: B/16, 1072 tokens). Logits and softmax in float32; ``mask`` [B, 1, 1, S]
    (True = attend) hides keys.
    """
    scale = 1.0 / np.sqrt(q.shape[-1])
    qh, kh, vh = (a.transpose(0, 2, 1, 3) for a in (q, k, v))  # [B, H, N|S, Dh]
    logits = jnp.einsum("bhnd,bhsd->bhns", qh, kh, preferred_element_type=jnp.float32) * scale
    if mask is not None:
        logits = jnp.where(mask, logits, jnp.finfo(jnp.float32).min)
    weights = jax.nn.softmax(logits, axis=-1).astype(v.dtype)
    return jnp.einsum("bhns,bhsd->bhnd", weights, vh).transpose(0, 2, 1, 3)


class Attention(nnx.Module):
    """Multi-head dot-product attention: queries [B, N, D], keys/values [B, S, D] -> [B, N, D].

    Self-attention when ``context`` is None. ``mask`` [B, S] (True = attend) hides padded
    keys. The XLA path is :func:`attention_xla` (logits and softmax in float32);
    ``implementation="cudnn"`` selects cuDNN flash attention on GPU through
    ``jax.nn.dot_product_attention``.
    """

    def __init__(self, width: int, num_heads: int, *, implementation: str | None = None,
                 dtype: Any, param_dtype: Any, rngs: nnx.Rngs):
        if width % num_heads:
            raise ValueError(f"attention width {width} is not divisible by num_heads {num_heads}")
        self.num_heads = num_heads
        self.implementation = implementation
        head_dim = width // num_heads
        kw = dict(dtype=dtype, param_dtype=param_dtype, kernel_init=_dense_init, rngs=rngs)
        self.query = nnx.LinearGeneral(width, (num_heads, head_dim), **kw)
        self.key = nnx.LinearGeneral(width, (num_heads, head_dim), **kw)
        self.value = nnx.LinearGeneral(width, (num_heads, head_dim), **kw)
        self.out = nnx.LinearGeneral((num_heads, head_dim), width, axis=(-2, -1), **kw)

    def __call__(self, x: Array, context: Array | None = None, mask: Array | None = None) -> Array:
        context = x if context is None else context
        q, k, v = self.query(x), self.key(context), self.value(context)  # [B, N|S, H, Dh]
        if mask is not None:
            mask = jnp.asarray(mask, bool)[:, None, None, :]  # [B, 1, 1, S]
        if self.implementation in (None, "xla"):
            y = attention_xla(q, k, v, mask)
        else:
            y = jax.nn.dot_product_attention(q, k, v, mask=mask,
                                             implementation=self.implementation)
        return self.out(y)


class LayerScale(nnx.Module):
    """Per-channel residual-branch scale [..., D] * gamma [D] (Touvron et al., CaiT, ICCV 2021).

    DINOv2 puts one after the attention and one after the MLP of every block, with gamma
    initialised to 1e-5, so a deep network starts close to the identity.
    """

    def __init__(self, width: int, init: float, *, param_dtype: Any):
        self.gamma = nnx.Param(jnp.full((width,), init, param_dtype))

    def __call__(self, x: Array) -> Array:
        return x * self.gamma[...].astype(x.dtype)


def _layerscale(cfg: ViTConfig) -> LayerScale | None:
    if cfg.layerscale_init is None:
        return nnx.data(None)
    return LayerScale(cfg.width, cfg.layerscale_init, param_dtype=cfg.param_dtype)


def _scaled(scale: LayerScale | None, x: Array) -> Array:
    return x if scale is None else scale(x)


class EncoderBlock(nnx.Module):
    """Pre-LN transformer block: x + Attn(LN(x)), then x + MLP(LN(x)). [B, N, D] -> [B, N, D].

    With ``cfg.layerscale_init`` each branch is multiplied by a :class:`LayerScale` first.
    """

    def __init__(self, cfg: ViTConfig, *, rngs: nnx.Rngs):
        kw = dict(dtype=cfg.dtype, param_dtype=cfg.param_dtype, rngs=rngs)
        self.norm1 = LayerNorm(cfg.width, epsilon=cfg.layernorm_epsilon, **kw)
        self.attn = Attention(cfg.width, cfg.num_heads, implementation=cfg.attention_impl, **kw)
        self.norm2 = LayerNorm(cfg.width, epsilon=cfg.layernorm_epsilon, **kw)
        self.mlp = Mlp(cfg.width, cfg.mlp_dim, **kw)
        self.ls1 = _layerscale(cfg)
        self.ls2 = _layerscale(cfg)

    def __call__(self, x: Array, mask: Array | None = None) -> Array:
        x = x + _scaled(self.ls1, self.attn(self.norm1(x), mask=mask))
        return x + _scaled(self.ls2, self.mlp(self.norm2(x)))


class CrossAttentionBlock(nnx.Module):
    """CroCo decoder block (Weinzaepfel et al., NeurIPS 2022), pre-LN, with optional LayerScale.

    ``(x [B, N, D], context [B, S, D]) -> [B, N, D]``: x + SelfAttn(LN(x)), then
    x + CrossAttn(LN(x), LN(context)) (queries from x, keys and values from the context), then
    x + MLP(LN(x)). The context is not updated. Sizes, dtypes and LayerScale come from ``cfg``.
    """

    def __init__(self, cfg: ViTConfig, *, rngs: nnx.Rngs):
        kw = dict(dtype=cfg.dtype, param_dtype=cfg.param_dtype, rngs=rngs)
        eps = cfg.layernorm_epsilon
        self.norm1 = LayerNorm(cfg.width, epsilon=eps, **kw)
        self.attn = Attention(cfg.width, cfg.num_heads, implementation=cfg.attention_impl, **kw)
        self.norm2 = LayerNorm(cfg.width, epsilon=eps, **kw)
        self.norm_context = LayerNorm(cfg.width, epsilon=eps, **kw)
        self.cross_attn = Attention(cfg.width, cfg.num_heads, implementation=cfg.attention_impl,
                                    **kw)
        self.norm3 = LayerNorm(cfg.width, epsilon=eps, **kw)
        self.mlp = Mlp(cfg.width, cfg.mlp_dim, **kw)
        self.ls1 = _layerscale(cfg)
        self.ls2 = _layerscale(cfg)
        self.ls3 = _layerscale(cfg)

    def __call__(self, x: Array, context: Array) -> Array:
        x = x + _scaled(self.ls1, self.attn(self.norm1(x)))
        x = x + _scaled(self.ls2, self.cross_attn(self.norm2(x), self.norm_context(context)))
        return x + _scaled(self.ls3, self.mlp(self.norm3(x)))


def _apply_block(block: EncoderBlock, x: Array, mask: Array | None) -> Array:
    return block(x, mask)


_apply_block_remat = nnx.remat(_apply_block)


def _apply_cross(block: CrossAttentionBlock, x: Array, context: Array) -> Array:
    return block(x, context)


_apply_cross_remat = nnx.remat(_apply_cross)


def apply_cross_block(block: CrossAttentionBlock, x: Array, context: Array, *,
                      remat: bool = False) -> Array:
    """``block(x, context)``, rematerialised in the backward pass when ``remat``."""
    return (_apply_cross_remat if remat else _apply_cross)(block, x, context)


class ConvStem(nnx.Module):
    """Patch embedding by early convolutions (Xiao et al., NeurIPS 2021): [B, H, W, 3] ->
    [B, H / patch, W / patch, width].

    log2(patch) 3x3 convolutions of stride 2 ('SAME' padding), each followed by a per-pixel
    LayerNorm over channels (ConvNeXt's; the paper's BatchNorm would need batch statistics, and
    a norm over the image would make every token depend on the whole tile) and GELU, with the
    channels doubling to the width (at least 16 in the first), then a 1x1 projection to the
    width. A token sees a little more than its patch, and the image is filtered before it is
    cut into tokens, which the paper found to make ViTs converge faster and less sensitive to
    the optimiser's settings.
    """

    def __init__(self, width: int, patch_size: int, *, dtype: Any, param_dtype: Any,
                 rngs: nnx.Rngs):
        n = int(patch_size).bit_length() - 1  # patch = 2**n
        channels = [max(16, width >> (n - 1 - i)) for i in range(n)]
        kw = dict(dtype=dtype, param_dtype=param_dtype, rngs=rngs)
        self.convs = nnx.List([
            nnx.Conv(c_in, c_out, kernel_size=(3, 3), strides=(2, 2), padding="SAME", **kw)
            for c_in, c_out in zip([3, *channels[:-1]], channels)])
        self.norms = nnx.List([nnx.LayerNorm(c, epsilon=1e-6, **kw) for c in channels])
        self.proj = nnx.Conv(channels[-1], width, kernel_size=(1, 1), **kw)

    def __call__(self, x: Array) -> Array:
        for conv, norm in zip(self.convs, self.norms):
            x = jax.nn.gelu(norm(conv(x)))
        return self.proj(x)


class ViT(nnx.Module):
    """ViT encoder with optional extra (prior) tokens and register tokens.

    ``__call__(images [B, H, W, 3], extra_tokens [B, E, D] | None, extra_mask [B, E] | None,
    layers=(), patch_offsets [B, P, D] | None)`` returns ``{"patch_tokens": [B, P, D], "extra_tokens": [B, E, D],
    "register_tokens": [B, R, D], "layers": (L x [B, P, D])}`` (the last three only when
    present), all after the final LayerNorm, with P = (H / patch) * (W / patch) in row-major
    order. ``layers`` names blocks (0-based) whose patch-token outputs are returned as well, in
    the manner of DINOv2's ``get_intermediate_layers(norm=True)``, for dense heads such as DPT.
    H and W must be multiples of the patch size but need not equal the native ``image_size``:
    the position embedding follows the grid.
    Extra tokens get no position embedding here; the caller adds whatever identifies them.
    ``patch_offsets`` are added to the patch embeddings (a pretrained stem's features, say).
    """

    def __init__(self, cfg: ViTConfig, *, rngs: nnx.Rngs):
        self.cfg = cfg
        kw = dict(dtype=cfg.dtype, param_dtype=cfg.param_dtype, rngs=rngs)
        p = cfg.patch_size
        if cfg.stem == "conv":
            self.patch_embed = ConvStem(cfg.width, p, **kw)
        else:
            self.patch_embed = nnx.Conv(3, cfg.width, kernel_size=(p, p), strides=(p, p),
                                        padding="VALID", **kw)
        gh, gw = cfg.native_grid
        if cfg.posemb == "learned":
            init = nnx.initializers.normal(1.0 / np.sqrt(cfg.width))
            self.posemb = nnx.Param(init(rngs.params(), (gh * gw, cfg.width), cfg.param_dtype))
        else:
            self.posemb = nnx.data(None)
        if cfg.num_registers:
            init = nnx.initializers.normal(0.02)
            self.registers = nnx.Param(
                init(rngs.params(), (cfg.num_registers, cfg.width), cfg.param_dtype))
        else:
            self.registers = nnx.data(None)
        self.blocks = nnx.List([EncoderBlock(cfg, rngs=rngs) for _ in range(cfg.depth)])
        self.norm = LayerNorm(cfg.width, epsilon=cfg.layernorm_epsilon, **kw)

    def grid(self, image_hw: tuple[int, int]) -> tuple[int, int]:
        """Patch grid (gh, gw) of an image of size ``image_hw``; raises if not patch-aligned."""
        h, w = image_hw
        p = self.cfg.patch_size
        if h % p or w % p:
            raise ValueError(
                f"image size {h}x{w} is not a multiple of the patch size {p}; resize or pad the "
                f"input to {-(-h // p) * p}x{-(-w // p) * p}"
            )
        return h // p, w // p

    def position_embedding(self, grid: tuple[int, int]) -> Array:
        """[gh * gw, D] position embedding for a patch grid, in the compute dtype."""
        if self.cfg.posemb == "learned":
            pe = resize_posemb(self.posemb[...], self.cfg.native_grid, grid)
        else:
            pe = posemb_sincos_2d(*grid, self.cfg.width)
        return pe.astype(self.cfg.dtype)

    def embed_patches(self, images: Array) -> Array:
        """[B, H, W, 3] -> patch tokens with position embedding [B, P, D]."""
        if images.ndim != 4:
            raise ValueError(f"ViT expects images [B, H, W, 3], got shape {images.shape}")
        grid = self.grid(images.shape[1:3])
        x = self.patch_embed(to_model_range(images, self.cfg.dtype))
        x = x.reshape(x.shape[0], grid[0] * grid[1], self.cfg.width)
        return x + self.position_embedding(grid)[None]

    def __call__(self, images: Array, extra_tokens: Array | None = None,
                 extra_mask: Array | None = None, layers: tuple[int, ...] = (),
                 patch_offsets: Array | None = None) -> dict[str, Array]:
        cfg = self.cfg
        layers = tuple(int(i) for i in layers)
        if any(not 0 <= i < cfg.depth for i in layers):
            raise ValueError(f"layers {layers} must be block indices in [0, {cfg.depth})")
        x = self.embed_patches(images)
        b, num_patches = x.shape[:2]
        if patch_offsets is not None:
            if patch_offsets.shape != x.shape:
                raise ValueError(f"patch_offsets must be [B, P, D] = {x.shape}, got "
                                 f"{patch_offsets.shape}")
            x = x + patch_offsets.astype(cfg.dtype)
        parts, masks = [x], [jnp.ones((b, num_patches), bool)]
        num_extra = 0
        if extra_tokens is not None:
            if extra_tokens.ndim != 3 or extra_tokens.shape[::2] != (b, cfg.width):
                raise ValueError(
                    f"extra_tokens must be [B={b}, E, D={cfg.width}], got {extra_tokens.shape}")
            num_extra = extra_tokens.shape[1]
            parts.append(extra_tokens.astype(cfg.dtype))
            masks.append(jnp.ones((b, num_extra), bool) if extra_mask is None
                         else jnp.broadcast_to(jnp.asarray(extra_mask, bool), (b, num_extra)))
        elif extra_mask is not None:
            raise ValueError("extra_mask given without extra_tokens")
        if self.registers is not None:
            reg = jnp.broadcast_to(self.registers[...].astype(cfg.dtype)[None],
                                   (b, cfg.num_registers, cfg.width))
            parts.append(reg)
            masks.append(jnp.ones((b, cfg.num_registers), bool))
        x = jnp.concatenate(parts, axis=1)
        mask = None if extra_mask is None else jnp.concatenate(masks, axis=1)
        apply = _apply_block_remat if cfg.remat else _apply_block
        hooked = {}
        for i, block in enumerate(self.blocks):
            x = apply(block, x, mask)
            if i in layers:
                hooked[i] = x[:, :num_patches]
        x = self.norm(x)
        out = {"patch_tokens": x[:, :num_patches]}
        if layers:
            out["layers"] = tuple(self.norm(hooked[i]) for i in layers)
        if extra_tokens is not None:
            out["extra_tokens"] = x[:, num_patches:num_patches + num_extra]
        if self.registers is not None:
            out["register_tokens"] = x[:, num_patches + num_extra:]
        return out


def count_params(module: nnx.Module) -> int:
    """Number of scalar parameters of a module (works on ``nnx.eval_shape`` abstract modules)."""
    leaves = jax.tree_util.tree_leaves(nnx.state(module, nnx.Param))
    return int(sum(np.prod(x.shape) for x in leaves))
