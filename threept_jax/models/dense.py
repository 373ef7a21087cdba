"""The dense cell detector: every part of a cell, every place of a full image, one pass.

3PT-D asks one part per 128 px tile and learns boxes one-to-few by Hungarian matching; on a
cell's images it learns about a tenth as fast per CPU minute as a standard detector
(docs/training.md, "Adapted 3PT-D against a standard detector"). This is the standard recipe
for the cell's closed set of parts (issue 38): a small convolutional backbone (stride-2 3x3
convolutions with BatchNorm and SiLU, residual blocks), a top-down feature pyramid over strides
8, 16 and 32 (Lin et al., CVPR 2017), and a head shared by the levels with separate
classification and box branches (FCOS, Tian et al., ICCV 2019; YOLOX's decoupled head). Each
place of each level predicts one logit per part and its distances to the box's four sides.

Shapes: B images, H W input size (multiples of 32), A anchor points over all levels, C parts,
F channels. Boxes are xyxy in pixel-edge coordinates of the network's input.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from threept_jax.models.heads import logit

Array = jax.Array

#: The pyramid's strides, finest first.
STRIDES = (8, 16, 32)


@dataclasses.dataclass(frozen=True)
class DenseConfig:
    """The dense cell detector.

    Attributes:
      num_classes: parts of the cell (the closed set it is trained on).
      width: channels of the first stage; stage i has ``width * 2**i`` (5 stages, strides 2-32).
      depths: residual blocks after the downsampling convolution of stages 2-5.
      neck_width: channels of the pyramid and the head.
      class_prior: initial probability of every logit (focal-loss prior init, RetinaNet).
      image_size: (H, W) the network sees; a camera image is scaled to fit and padded.
    """

    num_classes: int
    width: int = 16
    depths: tuple[int, ...] = (1, 2, 2, 1)
    neck_width: int = 64
    class_prior: float = 0.01
    image_size: tuple[int, int] = (256, 320)
    dtype: Any = jnp.float32
    param_dtype: Any = jnp.float32

    def __post_init__(self):
        if self.num_classes < 1:
            raise ValueError(f"num_classes must be >= 1, got {self.num_classes}")
        h, w = self.image_size
        if h % STRIDES[-1] or w % STRIDES[-1] or h <= 0 or w <= 0:
            raise ValueError(f"image_size {self.image_size} must be positive multiples of "
                             f"{STRIDES[-1]} (the coarsest stride)")
        if len(self.depths) != 4:
            raise ValueError(f"depths names the blocks of stages 2-5: 4 numbers, got "
                             f"{self.depths}")


def anchor_points(image_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Centres [A, 2] (x, y pixels) and strides [A] of every place of every level, finest
    level first, row-major within a level: the order of the head's outputs."""
    h, w = image_size
    centres, strides = [], []
    for s in STRIDES:
        y, x = np.mgrid[:h // s, :w // s].astype(np.float32)
        centres.append(np.stack([x.ravel(), y.ravel()], -1) * s + s / 2)
        strides.append(np.full(x.size, s, np.float32))
    return np.concatenate(centres), np.concatenate(strides)


class ConvBN(nnx.Module):
    """Convolution, BatchNorm, SiLU: [B, H, W, Fin] -> [B, H / stride, W / stride, Fout]."""

    def __init__(self, c_in: int, c_out: int, kernel: int = 3, stride: int = 1, *,
                 dtype: Any, param_dtype: Any, rngs: nnx.Rngs):
        self.conv = nnx.Conv(c_in, c_out, (kernel, kernel), strides=(stride, stride),
                             padding="SAME", use_bias=False, dtype=dtype,
                             param_dtype=param_dtype, rngs=rngs)
        # Momentum 0.97: the running statistics follow a 10-minute run's few thousand steps.
        self.norm = nnx.BatchNorm(c_out, momentum=0.97, epsilon=1e-3, dtype=jnp.float32,
                                  param_dtype=param_dtype, rngs=rngs)

    def __call__(self, x: Array) -> Array:
        return jax.nn.silu(self.norm(self.conv(x)))


class Residual(nnx.Module):
    """Two 3x3 ConvBN with a skip connection (ResNet's basic block)."""

    def __init__(self, c: int, **kw):
        self.a = ConvBN(c, c, **kw)
        self.b = ConvBN(c, c, **kw)

    def __call__(self, x: Array) -> Array:
        return x + self.b(self.a(x))


def _upsample(x: Array) -> Array:
    b, h, w, c = x.shape
    return jax.image.resize(x, (b, 2 * h, 2 * w, c), "nearest")


class DenseDetector(nnx.Module):
    """``__call__(images [B, H, W, 3] in [0, 1]) -> {"logits": [B, A, C], "boxes": [B, A, 4]}``
    (float32; boxes xyxy in input pixels, anchors in :func:`anchor_points` order)."""

    def __init__(self, cfg: DenseConfig, *, rngs: nnx.Rngs):
        self.cfg = cfg
        kw = dict(dtype=cfg.dtype, param_dtype=cfg.param_dtype, rngs=rngs)
        c = [cfg.width * 2 ** i for i in range(5)]
        self.stem = ConvBN(3, c[0], stride=2, **kw)
        self.down = nnx.List([ConvBN(a, b, stride=2, **kw) for a, b in zip(c[:-1], c[1:])])
        self.blocks = nnx.List([nnx.List([Residual(ch, **kw) for _ in range(n)])
                                for ch, n in zip(c[1:], cfg.depths)])
        f = cfg.neck_width
        self.lateral = nnx.List([ConvBN(ch, f, kernel=1, **kw) for ch in c[2:]])
        self.smooth = nnx.List([ConvBN(f, f, **kw) for _ in STRIDES])
        self.cls_branch = nnx.List([ConvBN(f, f, **kw) for _ in range(2)])
        self.box_branch = nnx.List([ConvBN(f, f, **kw) for _ in range(2)])
        self.cls_out = nnx.Conv(f, cfg.num_classes, (1, 1), dtype=cfg.dtype,
                                param_dtype=cfg.param_dtype,
                                kernel_init=nnx.initializers.normal(0.01),
                                bias_init=nnx.initializers.constant(logit(cfg.class_prior)),
                                rngs=rngs)
        # Zero kernel: every place starts with the same box, 2 strides to each side.
        self.box_out = nnx.Conv(f, 4, (1, 1), dtype=cfg.dtype, param_dtype=cfg.param_dtype,
                                kernel_init=nnx.initializers.zeros,
                                bias_init=nnx.initializers.constant(np.log(2.0)), rngs=rngs)

    def features(self, images: Array) -> list[Array]:
        """The pyramid [B, H / s, W / s, F] for s in :data:`STRIDES`."""
        x = self.stem(images.astype(self.cfg.dtype))
        stages = []
        for down, blocks in zip(self.down, self.blocks):
            x = down(x)
            for block in blocks:
                x = block(x)
            stages.append(x)
        top = None
        out = []
        for lateral, smooth, x in reversed(list(zip(self.lateral, self.smooth, stages[1:]))):
            y = lateral(x)
            if top is not None:
                y = y + _upsample(top)
            top = y
            out.append(smooth(y))
        return out[::-1]

    def __call__(self, images: Array) -> dict[str, Array]:
        h, w = images.shape[1:3]
        if (h, w) != tuple(self.cfg.image_size):
            raise ValueError(f"images are {h}x{w}, the detector takes {self.cfg.image_size}: "
                             "scale and pad them with data.dense_input.letterbox")
        logits, ltrb = [], []
        for x in self.features(images):
            b = x.shape[0]
            y = x
            for layer in self.cls_branch:
                y = layer(y)
            logits.append(self.cls_out(y).reshape(b, -1, self.cfg.num_classes))
            y = x
            for layer in self.box_branch:
                y = layer(y)
            ltrb.append(self.box_out(y).reshape(b, -1, 4))
        logits = jnp.concatenate(logits, 1).astype(jnp.float32)
        # Distances in strides, exp of a clipped output (FCOS): positive, scale-free.
        dist = jnp.exp(jnp.clip(jnp.concatenate(ltrb, 1).astype(jnp.float32), -6.0, 6.0))
        centres, strides = (jnp.asarray(v) for v in anchor_points(self.cfg.image_size))
        dist = dist * strides[None, :, None]
        c = centres[None]
        boxes = jnp.concatenate([c - dist[..., :2], c + dist[..., 2:]], -1)
        return {"logits": logits, "boxes": boxes}


def decode(logits: Array, boxes: Array, *, max_candidates: int = 1000, max_detections: int = 100,
           nms_iou: float = 0.6) -> dict[str, Array]:
    """One image's detections from the head's outputs: logits [A, C], boxes [A, 4] ->
    ``boxes`` [N, 4], ``scores`` [N], ``classes`` [N] int32 and ``valid`` [N] bool, best first
    (N = ``max_detections``).

    The ``max_candidates`` best (place, part) scores, then NMS within each part (boxes of
    different parts are shifted apart so one NMS pass never lets them suppress each other).
    """
    from threept_jax.geometry.boxes import nms

    a, c = logits.shape
    k = min(max_candidates, a * c)
    scores, flat = jax.lax.top_k(jax.nn.sigmoid(logits).reshape(-1), k)
    place, cls = flat // c, (flat % c).astype(jnp.int32)
    cand = boxes[place]
    offset = (cls * (jnp.max(jnp.abs(boxes)) * 2 + 1.0))[:, None].astype(jnp.float32)
    keep, valid = nms(cand + offset, scores, nms_iou, max_detections)
    return {"boxes": cand[keep], "scores": jnp.where(valid, scores[keep], 0.0),
            "classes": cls[keep], "valid": valid}
