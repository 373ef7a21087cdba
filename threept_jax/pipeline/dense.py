"""The dense cell detector on a camera image: letterbox, one network pass, decoding, boxes
back in the image's pixels; shared by training's evaluation and inference."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from threept_jax.data.dense_input import letterbox
from threept_jax.models.dense import DenseDetector, decode


@functools.lru_cache(maxsize=8)
def _compiled(graphdef: nnx.GraphDef):
    """The jitted network and decoding of one network structure, shared by every
    :class:`ImageBoxes` of it (a training run's snapshots compile once)."""

    @jax.jit
    def run(state, canvas):
        out = nnx.merge(graphdef, state)(canvas[None].astype(jnp.float32) / 255.0)
        return decode(out["logits"][0], out["boxes"][0])

    return run


class ImageBoxes:
    """``(image uint8 [H, W, 3]) -> boxes [n, 4] xyxy (image pixels, clipped), scores [n],
    classes [n]`` (output indices), best first, every score kept (the caller thresholds).
    One compiled function for every image size (images are letterboxed to the network's)."""

    def __init__(self, network: DenseDetector):
        network.eval()
        self.image_size = network.cfg.image_size
        graphdef, self._state = nnx.split(network)
        self._run = _compiled(graphdef)

    def __call__(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        canvas, s = letterbox(np.asarray(image), self.image_size)
        out = jax.device_get(self._run(self._state, jnp.asarray(canvas)))
        h, w = image.shape[:2]
        v = out["valid"]
        boxes = np.clip(out["boxes"][v] / s, 0, [w, h, w, h])
        return boxes, out["scores"][v], out["classes"][v]
