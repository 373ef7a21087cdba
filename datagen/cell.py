"""Robot-cell scenes: one fixed camera above a tray at a known working distance.

A bin-picking or insertion cell looks nothing like the random views of the zero-shot data: one
camera, calibrated once, looks down into a tray at a working distance the integrator knows, and
the parts of the cell appear 60-300 px across. 3PT uses exactly that knowledge at inference
("at inference time, we assume a defined depth range"): the depth range fixes the pan-and-scan
scale (one or two scales instead of three). :func:`design_cell` draws such a cell once per
dataset from the dataset's seed and its parts' diameters; every scene of the dataset, in every
split and shard, is a capture of it with small jitter (the tray moves, the camera mount is
re-seated), and the dataset records the cell (``cell.json`` at its root, read by
``threept_jax.data.bop.load_cell``) so that detection uses its depth range by default.

Geometry (mm, world z up, the tray floor at z = 0 centred on the origin, as ``layouts.Bin``):

* intrinsics: ``cameras.sample_intrinsics`` at the dataset's resolution (40-70 degree FOV);
* working distance D (optical centre to the tray floor along the axis): the median part
  diameter projects to ``MEDIAN_PART_SHARE`` of the longer image side at D (farther when the
  largest part would then come closer to the camera than 40 % of D);
* tray: its inner footprint fills ``TRAY_FILL`` of the image at the floor, walls
  ``tray_height`` high (a shallow tray: parts lie in one or two layers);
* each capture: distance D x (1 +- ``DISTANCE_JITTER``), the axis tilted up to ``TILT_DEG``
  from vertical, aimed within ``AIM_JITTER`` of the tray size around its centre, rolled by at
  most ``ROLL_DEG``;
* a rig of V > 1 calibrated cameras (``datagen.generate --layout cell --views V``): every
  camera aims at the capture's one aim point from ``RIG_TILT_DEG`` (+- ``RIG_JITTER_DEG``) off
  the vertical, the V of them evenly spread in azimuth (+- ``RIG_JITTER_DEG``), each at its own
  jittered distance and roll: two cameras look at the tray from 30 degrees apart, a baseline
  of about half the working distance (a stereo rig over a bin), where one camera's captures
  move by 14-140 mm;
* depth range of part centres (what detection assumes): from the nearest capture distance less
  the tray height and the tilt's rise across the tray, to the farthest distance plus that rise
  (:meth:`Cell.depth_range`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from datagen import cameras as cams
from datagen import layouts as L

#: Median part diameter at the working distance, as a share of the longer image side (100-140 px
#: at 640 x 480: parts then span ~60-300 px).
MEDIAN_PART_SHARE = (0.16, 0.22)
#: Share of the image side the tray's inner footprint fills at the floor.
TRAY_FILL = 0.85
#: Per-capture jitter of the rig: distance (fraction), tilt from vertical (degrees), aim point
#: (fraction of the tray size), roll about the axis (degrees).
DISTANCE_JITTER = 0.05
TILT_DEG = 8.0
AIM_JITTER = 0.05
ROLL_DEG = 3.0
#: A rig of several cameras: each camera's axis off the vertical, and the jitter of that tilt
#: and of the cameras' azimuths (degrees).
RIG_TILT_DEG = 15.0
RIG_JITTER_DEG = 3.0


@dataclasses.dataclass(frozen=True)
class Cell:
    """One cell: camera intrinsics, working distance and tray (module docstring).

    Attributes:
      resolution: (W, H) pixels of the camera.
      K: 3x3 intrinsics as nested tuples (pixels; fx may differ from fy).
      working_distance: D, mm from the optical centre to the tray floor along the axis.
      tray_inner: (x, y) inner footprint of the tray, mm.
      tray_height: wall height, mm.
      max_height: the highest a part's centre gets above the floor (mm): a part of the
        largest diameter resting on the rim, ``tray_height`` + half that diameter.
      views: cameras in the rig (1: one camera; V > 1: the rig of the module docstring).
    """

    resolution: tuple[int, int]
    K: tuple[tuple[float, float, float], ...]
    working_distance: float
    tray_inner: tuple[float, float]
    tray_height: float
    max_height: float
    views: int = 1

    @property
    def max_tilt_deg(self) -> float:
        """The most a camera's axis leans from the vertical (degrees)."""
        return TILT_DEG if self.views == 1 else RIG_TILT_DEG + RIG_JITTER_DEG

    @property
    def tray(self) -> L.Bin:
        return L.Bin(self.tray_inner, height=self.tray_height, wall=10.0)

    @property
    def distance_range(self) -> tuple[float, float]:
        """Working distances the captures use (mm)."""
        d = self.working_distance
        return d * (1 - DISTANCE_JITTER), d * (1 + DISTANCE_JITTER)

    def depth_range(self) -> tuple[float, float]:
        """(zmin, zmax) camera depth of any part centre in any capture (mm).

        A point at height h <= ``max_height`` above the floor, offset by at most the tray's
        half diagonal s (grown by the aim jitter) from the aim point, seen along an axis tilted
        by theta <= ``TILT_DEG``: its depth differs from the capture's working distance by at
        most h + s sin(theta) toward the camera and s sin(theta) away from it.
        """
        lo, hi = self.distance_range
        s = 0.5 * math.hypot(*self.tray_inner) * (1 + 2 * AIM_JITTER)
        rise = s * math.sin(math.radians(self.max_tilt_deg))
        return lo - self.max_height - rise, hi + rise

    def to_json(self) -> dict:
        zmin, zmax = self.depth_range()
        return {"resolution": list(self.resolution), "cam_K": [v for row in self.K for v in row],
                "working_distance_mm": self.working_distance,
                "distance_range_mm": list(self.distance_range),
                "tray_inner_mm": list(self.tray_inner), "tray_height_mm": self.tray_height,
                "max_part_height_mm": self.max_height, "views": self.views,
                "depth_range_mm": [zmin, zmax]}


def design_cell(rng: np.random.Generator, diameters: Sequence[float],
                resolution: tuple[int, int], views: int = 1) -> Cell:
    """The cell of a dataset whose parts have ``diameters`` (mm), seen by ``views`` cameras,
    drawn from ``rng`` (the same draws whatever ``views``)."""
    if views < 1:
        raise ValueError(f"a cell needs at least one camera, got views={views}")
    d = np.asarray(diameters, np.float64)
    if d.size == 0 or not np.all(np.isfinite(d) & (d > 0)):
        raise ValueError(f"a cell needs the positive diameters (mm) of its parts, got {d}")
    W, H = resolution
    K = cams.sample_intrinsics(rng, W, H)
    median = float(np.median(d))
    distance = K[0, 0] * median / (rng.uniform(*MEDIAN_PART_SHARE) * max(W, H))
    height = float(rng.uniform(0.3, 0.6) * median)
    while True:
        # Parts must fit under the camera: at least one largest part (+ margin) across.
        inner = (max(TRAY_FILL * W * distance / K[0, 0], 1.3 * d.max()),
                 max(TRAY_FILL * H * distance / K[1, 1], 1.3 * d.max()))
        cell = Cell((int(W), int(H)), tuple(tuple(float(v) for v in row) for row in K),
                    float(distance), (float(inner[0]), float(inner[1])), height,
                    height + 0.5 * float(d.max()), int(views))
        if cell.depth_range()[0] >= 0.4 * distance:
            return cell
        distance *= 1.25


def capture(rng: np.random.Generator, cell: Cell) -> tuple[np.ndarray, np.ndarray]:
    """One capture of the cell: (K [V, 3, 3], T_cam_world [V, 4, 4]) of its V cameras, with
    the rig's jitter (module docstring)."""
    K = np.asarray(cell.K, np.float64)
    if cell.views == 1:
        dist = rng.uniform(*cell.distance_range)
        tilts = [math.radians(rng.uniform(0.0, TILT_DEG))]
        azimuths = [rng.uniform(0.0, 2 * math.pi)]
        aim = np.array([*(rng.uniform(-AIM_JITTER, AIM_JITTER, 2) * cell.tray_inner), 0.0])
        dists = [dist]
    else:
        aim = np.array([*(rng.uniform(-AIM_JITTER, AIM_JITTER, 2) * cell.tray_inner), 0.0])
        phase = rng.uniform(0.0, 2 * math.pi)
        jitter = rng.uniform(-RIG_JITTER_DEG, RIG_JITTER_DEG, (cell.views, 2))
        tilts = np.radians(RIG_TILT_DEG + jitter[:, 0])
        azimuths = phase + 2 * np.pi * np.arange(cell.views) / cell.views + np.radians(jitter[:, 1])
        dists = rng.uniform(*cell.distance_range, cell.views)
    Ts = []
    for tilt, azimuth, dist in zip(tilts, azimuths, dists, strict=True):
        direction = np.array([math.sin(tilt) * math.cos(azimuth),
                              math.sin(tilt) * math.sin(azimuth), math.cos(tilt)])
        # Image "up" is world -y (the tray's far side up), whatever the tilt; never parallel.
        Ts.append(cams.look_at_camera(aim + dist * direction, aim, up=(0.0, 1.0, 0.0),
                                      roll_deg=rng.uniform(-ROLL_DEG, ROLL_DEG)))
    return np.repeat(K[None], cell.views, 0), np.stack(Ts)
