"""Which near-symmetric turn of a refined pose the image shows: the edges inside the outline.

A refined pose of a part with near symmetries (:func:`threept_jax.geometry.turns.
near_symmetry_turns`: a gear's tooth pitch, a hexagon's sixth) is right up to one of its turns:
the outline is the same, and only a small feature (a keyway, a flat) tells them apart. Each
candidate (the pose and the pose turned by each near symmetry, about the part's centre, so the
outline stays where it was fitted) is rendered as an edge map (silhouette, depth steps and
creases, :func:`threept_jax.render.raster.edges_from_geometry`) in a square window around the
part in every view, and scored by the share of its edge pixels that lie within
``NEAR_PX`` of an edge of the image (Canny, in the same window). The rendered edges of the
candidates differ only where the feature is, so the share differs only by how well the
feature is found. The best candidate is kept where it scores higher than the pose by ``MIN_GAIN``.

Measured offline on the demo's gear (40 teeth, one keyway; 35 found instances of 48 held-out
images, one view): the refined pose within 0.2 diameters (MSSD) for 2, the best of its 40 turns
picked by this score for 14 (docs/benchmarks.md, "Near-symmetric turns").
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from threept_jax.render import Renderer

#: Side of the square window a part is compared in (pixels, after scaling).
WINDOW = 192
#: The window is the part's projected box grown by this factor.
MARGIN = 1.15
#: A rendered edge pixel counts as found within this distance of an image edge (pixels).
NEAR_PX = 1.5
#: Canny thresholds on the window's grey image, blurred 3x3.
CANNY = (30, 90)
#: Parts smaller than this in a view (projected box side, pixels) are not judged there.
MIN_SIDE = 24
#: A turn replaces the pose only when its share beats the pose's by this much: a keyway's
#: edges are 1-3 % of a gear's, and a part's exact (undeclared) symmetries score equal up to
#: the rasteriser's rounding.
MIN_GAIN = 0.005


def _window(T_cam_obj: np.ndarray, K: np.ndarray, corners: np.ndarray, hw):
    """(A [2, 3] image -> window affine, K of the window) for the part's projected box, or
    None when it is too small or off the image."""
    p = corners @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    if np.any(p[:, 2] <= 1.0):
        return None
    uv = (p @ K.T)[:, :2] / p[:, 2:]
    (x0, y0), (x1, y1) = uv.min(0), uv.max(0)
    H, W = hw
    if max(x1 - x0, y1 - y0) < MIN_SIDE or x1 < 0 or y1 < 0 or x0 > W - 1 or y0 > H - 1:
        return None
    side = MARGIN * max(x1 - x0, y1 - y0)
    s = WINDOW / side
    ox, oy = 0.5 * (x0 + x1) - 0.5 * side, 0.5 * (y0 + y1) - 0.5 * side
    A = np.array([[s, 0.0, -s * ox], [0.0, s, -s * oy]])
    return A, np.vstack([A, [0.0, 0.0, 1.0]]) @ K


def _edge_distance(image: np.ndarray, A: np.ndarray) -> np.ndarray:
    """[WINDOW, WINDOW] distance (pixels) to the nearest Canny edge of the image's window."""
    crop = cv2.warpAffine(np.ascontiguousarray(image), A, (WINDOW, WINDOW),
                          flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    grey = cv2.GaussianBlur(cv2.cvtColor(crop, cv2.COLOR_RGB2GRAY), (3, 3), 0)
    edges = cv2.Canny(grey, *CANNY)
    return cv2.distanceTransform((edges == 0).astype(np.uint8), cv2.DIST_L2, 3)


def turn_scores(renderer: Renderer, corners: np.ndarray, candidates: np.ndarray,
                images: Sequence[np.ndarray], Ks: np.ndarray,
                T_cam_world: np.ndarray) -> np.ndarray | None:
    """[C] the share of each candidate's rendered edges found in the images (module docstring),
    summed over the views where the part (at ``candidates[0]``, world frame [C, 4, 4]) is
    judged; None when it is judged in none. ``corners`` [8, 3]: its bounding box (mm, object
    frame). A part's candidates are always as many (its turns and the pose): one compilation
    of the renderer per part."""
    found = np.zeros(len(candidates))
    total = np.zeros(len(candidates))
    for image, K, T_cw in zip(images, np.asarray(Ks, np.float64), np.asarray(T_cam_world)):
        T = np.einsum("ij,cjk->cik", T_cw, candidates)
        window = _window(T[0], K, corners, image.shape[:2])
        if window is None:
            continue
        A, K_win = window
        dist = _edge_distance(image, A)
        edges = np.asarray(renderer.render(T.astype(np.float32), K_win.astype(np.float32),
                                           (WINDOW, WINDOW), outputs=("edge",))["edge"])
        found += (edges & (dist <= NEAR_PX)[None]).sum((1, 2))
        total += edges.sum((1, 2))
    if not total.any():
        return None
    return found / np.maximum(total, 1)


def choose_turn(renderer: Renderer, corners: np.ndarray, pose: np.ndarray, turns: np.ndarray,
                images: Sequence[np.ndarray], Ks: np.ndarray,
                T_cam_world: np.ndarray) -> np.ndarray:
    """``pose`` (world, [4, 4]) or the turn of it (``pose @ turns[k]``, object-frame turns
    [M, 4, 4]) whose edges the images show best, where one beats ``pose`` by ``MIN_GAIN``."""
    candidates = np.concatenate([pose[None], np.einsum("ij,mjk->mik", pose, turns)])
    scores = turn_scores(renderer, corners, candidates, images, Ks, T_cam_world)
    if scores is None or scores[1:].max() <= scores[0] + MIN_GAIN:
        return pose
    return candidates[int(np.argmax(scores))]
