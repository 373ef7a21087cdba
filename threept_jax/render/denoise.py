"""Monte-Carlo noise removal for path-traced images with Intel Open Image Denoise (OIDN).

OIDN (the denoiser of Blender's Cycles; ``pyoidn`` on PyPI bundles the CPU library) is a
network trained on path-traced renders. It is fed what it was trained with: the linear (HDR)
colour and two auxiliary images of the same samples, the first-hit albedo and shading normal,
which carry the texture and geometry edges the noisy colour hides. ``MitsubaScene.render(...,
denoise=True)`` renders all three in one pass (Mitsuba's ``aov`` integrator) and calls
:func:`denoise`.

Determinism: on one machine (one instruction set) the output is a function of the inputs
alone, whatever the number of threads (tested); a dataset regenerated on another CPU family
may differ in the last bits.
"""

from __future__ import annotations

import threading

import numpy as np

_lock = threading.Lock()


def denoise(color: np.ndarray, albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Denoise linear RGB radiance ``color`` [H, W, 3] (>= 0, any scale) guided by the
    first-hit ``albedo`` [H, W, 3] in [0, 1] and shading ``normal`` [H, W, 3] (unit, any fixed
    frame; 0 where rays escape). Returns float32 linear RGB [H, W, 3], >= 0."""
    import pyoidn

    color = np.asarray(color, np.float32)
    if color.ndim != 3 or color.shape[-1] != 3:
        raise ValueError(f"color must be [H, W, 3] linear RGB, got shape {color.shape}")
    for name, aux in (("albedo", albedo), ("normal", normal)):
        if np.shape(aux) != color.shape:
            raise ValueError(f"{name} must have color's shape {color.shape}, got {np.shape(aux)}")
    if not np.isfinite(color).all():
        raise ValueError("color has NaN or inf pixels: the path tracer output is broken")
    albedo = np.clip(np.asarray(albedo, np.float32), 0.0, 1.0)
    normal = np.clip(np.asarray(normal, np.float32), -1.0, 1.0)
    with _lock:  # pyoidn shares one device and filter per process
        out = pyoidn.denoise(np.maximum(color, 0.0), albedo, normal, hdr=True, quality="high")
    return np.maximum(out, 0.0).astype(np.float32)
