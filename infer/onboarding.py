"""Onboarding: a CAD model becomes a detector query (prior tokens + template bank), cached.

For each object the 12 prior views and T templates are rendered with the bank camera
(``threept_jax.pipeline.onboarding.render_bank``, the same images training saw), resized to the
model's render size exactly as the training pipeline does, and embedded by the detector's object
tower. The result is cached on disk under a key made of the mesh file's bytes, the detector's
identity (``model_id``: workdir and step) and the rendering settings, so a second run onboards in
milliseconds and a changed mesh or checkpoint is never served stale.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import pathlib
from collections.abc import Mapping

import jax
import numpy as np
from flax import nnx
from tqdm import tqdm

from threept_jax.data.banks import BANK_SIZE, BANK_TEMPLATES, resize_renders
from threept_jax.data.files import atomic_savez
from threept_jax.models.configs import DetectorConfig
from threept_jax.models.detector import Detector
from threept_jax.pipeline.onboarding import render_bank
from threept_jax.render import Mesh, load_mesh, prepare_mesh

#: Model points kept per object for fitting boxes (object generation).
NUM_POINTS = 1024
#: Face budget of the mesh kept for rendering overlays and masks.
RENDER_FACES = 4096

CACHE_VERSION = 1


@dataclasses.dataclass(frozen=True, eq=False)
class OnboardedObject:
    """One object ready for detection.

    Attributes:
      obj_id: the caller's id (BOP obj_id).
      name: for messages and overlays.
      mesh: the model (mm), decimated to ``RENDER_FACES`` for rendering poses.
      diameter: mm.
      points: [N, 3] model points (vertices, subsampled) for box fitting.
      prior_tokens: [Np, D] object-tower prior tokens.
      template_bank: [T, E] unit template embeddings.
      template_rotations: [T, 3, 3] object-centred rotations of the templates.
      symmetries: [S, 4, 4] symmetry transforms, identity first.
      center: [3] centre of the bounding sphere the bank camera looks at (object frame, mm).
    """

    obj_id: int
    name: str
    mesh: Mesh
    diameter: float
    points: np.ndarray
    prior_tokens: np.ndarray
    template_bank: np.ndarray
    template_rotations: np.ndarray
    symmetries: np.ndarray
    center: np.ndarray


def _points(mesh: Mesh, n: int = NUM_POINTS) -> np.ndarray:
    v = np.asarray(mesh.vertices, np.float32)
    if len(v) <= n:
        return np.concatenate([v, np.repeat(v[:1], n - len(v), 0)])  # duplicates are harmless
    idx = np.random.default_rng(0).choice(len(v), n, replace=False)
    # The extreme vertices decide boxes: always keep them.
    extremes = np.concatenate([np.argmin(v, 0), np.argmax(v, 0)])
    idx[: len(extremes)] = extremes
    return v[idx]


class Onboarder:
    """Embeds objects with one detector (``model`` from ``infer.checkpoint.load_detector``)."""

    def __init__(self, model: Detector, config: DetectorConfig, model_id: str,
                 cache_dir: str | os.PathLike | None = None, num_templates: int = BANK_TEMPLATES,
                 bank_size: int = BANK_SIZE, template_chunk: int = 256):
        self.config = config
        self.model_id = model_id
        self.cache_dir = None if cache_dir is None else pathlib.Path(cache_dir)
        self.num_templates = int(num_templates)
        self.bank_size = int(bank_size)
        graphdef, params = nnx.split(model)
        self._params = params

        def embed(params, priors, templates):
            m = nnx.merge(graphdef, params)
            return m.embed_object(priors[None])[0], m.embed_templates(
                templates[None], chunk_size=template_chunk)[0]

        self._embed = jax.jit(embed)

    def _key(self, mesh_bytes: bytes) -> str:
        h = hashlib.sha256()
        h.update(mesh_bytes)
        h.update(json.dumps([CACHE_VERSION, self.model_id, self.num_templates, self.bank_size,
                             self.config.render_size]).encode())
        return h.hexdigest()[:32]

    def onboard(self, obj_id: int, mesh: str | os.PathLike | Mesh, units: str = "mm",
                progress: tqdm | None = None) -> OnboardedObject:
        """Onboard one object from a mesh file (units checked on load) or a ``Mesh``."""
        if isinstance(mesh, Mesh):
            model = mesh
            content = model.vertices.tobytes() + model.faces.tobytes()
        else:
            path = pathlib.Path(mesh)
            model = load_mesh(path, units=units)
            content = path.read_bytes() + units.encode()
        cache = None if self.cache_dir is None else self.cache_dir / f"{self._key(content)}.npz"
        sym = model.symmetries
        if cache is not None and cache.exists():
            with np.load(cache, allow_pickle=False) as z:
                prior, bank, rotations, symmetries, center = (
                    z["prior_tokens"], z["template_bank"], z["template_rotations"],
                    z["symmetries"], z["center"])
            if progress is not None:
                progress.update(12 + self.num_templates)
        else:
            rb = render_bank(model, obj_id, float(model.diameter), sym, self.bank_size,
                             self.num_templates,
                             on_views=None if progress is None else progress.update)
            size = self.config.render_size
            prior, bank = self._embed(self._params, resize_renders(rb.prior_rgb, size),
                                      resize_renders(rb.template_rgb, size))
            prior, bank = np.asarray(prior), np.asarray(bank)
            rotations, symmetries, center = rb.template_rotations, rb.symmetries, rb.center
            if cache is not None:
                atomic_savez(cache, prior_tokens=prior, template_bank=bank,
                              template_rotations=rotations, symmetries=symmetries, center=center)
        render_mesh = model if model.num_faces <= RENDER_FACES else prepare_mesh(
            model, max_faces=RENDER_FACES)
        return OnboardedObject(int(obj_id), model.name, render_mesh, float(model.diameter),
                               _points(model), prior, bank, np.asarray(rotations, np.float32),
                               np.asarray(symmetries, np.float32), np.asarray(center, np.float32))

    def onboard_all(self, meshes: Mapping[int, str | os.PathLike | Mesh], units: str = "mm",
                    show_progress: bool = True) -> list[OnboardedObject]:
        """Onboard every ``{obj_id: mesh}`` with one progress bar (views rendered/embedded)."""
        total = len(meshes) * (12 + self.num_templates)
        with tqdm(total=total, unit="view", desc="onboarding", disable=not show_progress,
                  dynamic_ncols=True) as bar:
            return [self.onboard(oid, m, units, bar) for oid, m in sorted(meshes.items())]
