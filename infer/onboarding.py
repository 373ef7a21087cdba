"""Onboarding: a CAD model becomes a detector query (prior tokens + template bank), cached.

For each object the 12 prior views and T templates are rendered with the bank camera at the
model's render size (``threept_jax.pipeline.onboarding.BankRenderer``: the function, size and
anti-aliasing that packed the training banks, so the images are those training saw) and embedded
by the detector's object tower, block by block (``template_chunk`` templates per block, 64 on
CPU: one compiled embedding for every object, and progress that counts views rendered *and*
embedded). The result is cached on disk under a key made of the mesh file's bytes, the
detector's identity (``model_id``: workdir and step) and the rendering settings, so a second run
onboards in milliseconds and a changed mesh or checkpoint is never served stale.

**Bank size.** Inference onboards ``ONBOARD_TEMPLATES`` = 1024 templates by default, not the
paper's 5140 (``threept_jax.data.banks.BANK_TEMPLATES``, still what training banks hold and
available with ``num_templates=5140``). The bank feeds the orientation distribution, from which
object generation takes the top-K rotations at least 45 degrees apart for the refiner; a grid
whose covering radius is below half that separation puts any two such peaks on distinct
templates. Covering radius of the super-Fibonacci grid (max over 200k random rotations, float64;
``bench/onboarding.py --coverage``): 512: 28.9, 768: 25.0, **1024: 22.1**, 2048: 17.2,
5140: 12.8 degrees; 1024 is the smallest grid of that ladder under 22.5 degrees, at a fifth of
the renders and embeddings.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import pathlib
import time
from collections.abc import Mapping

import jax
import numpy as np
from flax import nnx
from tqdm import tqdm

from threept_jax.data.banks import bank_symmetries
from threept_jax.data.files import atomic_savez
from threept_jax.geometry.grids import prior_view_rotations, super_fibonacci_rotations
from threept_jax.models.configs import DetectorConfig
from threept_jax.models.detector import Detector
from threept_jax.pipeline.detection import model_points
from threept_jax.pipeline.onboarding import BankRenderer
from threept_jax.render import Mesh, load_mesh, prepare_mesh

#: Face budget of the mesh kept for rendering overlays and masks.
RENDER_FACES = 4096

CACHE_VERSION = 2  # 2: renders at the model's render size, supersampled
#: Templates per object onboarded for inference by default (module docstring).
ONBOARD_TEMPLATES = 1024
#: Templates embedded per call (one compiled embedding for all objects; progress per block).
#: On CPU medium blocks are faster per template (S/16 at 112 px: 7.9 ms at 32 or 64, 10.1 at
#: 256, 11.1 at 512; 2-core CPU); accelerators take large ones.
CPU_TEMPLATE_CHUNK = 64
DEVICE_TEMPLATE_CHUNK = 256
#: Views of the object tower's prior (``grids.prior_view_rotations``).
NUM_PRIOR_VIEWS = 12


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


class Onboarder:
    """Embeds objects with one detector (``model`` from ``infer.checkpoint.load_detector``).

    ``timings[obj_id]``: seconds spent rendering and embedding the last onboarding of
    that object (zeros when it came from the cache), for benchmarks.
    """

    def __init__(self, model: Detector, config: DetectorConfig, model_id: str,
                 cache_dir: str | os.PathLike | None = None,
                 num_templates: int = ONBOARD_TEMPLATES, template_chunk: int | None = None):
        if template_chunk is None:
            template_chunk = (CPU_TEMPLATE_CHUNK if jax.default_backend() == "cpu"
                              else DEVICE_TEMPLATE_CHUNK)
        if num_templates < 1 or template_chunk < 1:
            raise ValueError(f"num_templates and template_chunk must be >= 1, got "
                             f"{num_templates} and {template_chunk}")
        self.config = config
        self.model_id = model_id
        self.cache_dir = None if cache_dir is None else pathlib.Path(cache_dir)
        self.num_templates = int(num_templates)
        self.template_chunk = min(int(template_chunk), self.num_templates)
        self.timings: dict[int, dict[str, float]] = {}
        graphdef, params = nnx.split(model)
        self._params = params

        def embed_priors(params, priors):
            return nnx.merge(graphdef, params).embed_object(priors[None])[0]

        def embed_templates(params, templates):
            return nnx.merge(graphdef, params).embed_templates(templates[None])[0]

        self._embed_priors = jax.jit(embed_priors)
        self._embed_templates = jax.jit(embed_templates)

    @property
    def views_per_object(self) -> int:
        """Renders (and embeddings) per object: the prior views and the templates."""
        return NUM_PRIOR_VIEWS + self.num_templates

    def _key(self, mesh_bytes: bytes) -> str:
        h = hashlib.sha256()
        h.update(mesh_bytes)
        h.update(json.dumps([CACHE_VERSION, self.model_id, self.num_templates,
                             self.config.render_size]).encode())
        return h.hexdigest()[:32]

    def _embed(self, model: Mesh, obj_id: int, progress: tqdm | None):
        """(prior tokens [Np, D], template bank [T, E], template rotations [T, 3, 3], bank
        renderer) of a model, rendered and embedded block by block."""
        size = self.config.render_size
        seconds = dict(render=0.0, embed=0.0)

        def stage(name, fn, *args):
            t0 = time.perf_counter()
            out = fn(*args)
            seconds[name] += time.perf_counter() - t0
            return out

        def embed(fn, images):
            return np.asarray(fn(self._params, images))  # np.asarray waits for the result

        render = stage("render", BankRenderer, model, size)
        priors = stage("render", render, prior_view_rotations())
        prior = stage("embed", embed, self._embed_priors, priors)
        if progress is not None:
            progress.update(len(priors))
        rotations = super_fibonacci_rotations(self.num_templates)
        c = self.template_chunk
        bank = []
        for start in range(0, len(rotations), c):
            R = rotations[start : start + c]
            n = len(R)
            images = stage("render", render, R)
            if n < c:  # pad the last block: one compiled embedding whatever T is
                images = np.concatenate([images, np.repeat(images[-1:], c - n, 0)])
            bank.append(stage("embed", embed, self._embed_templates, images)[:n])
            if progress is not None:
                progress.update(n)
        self.timings[int(obj_id)] = seconds
        return prior, np.concatenate(bank), rotations, render

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
        if cache is not None and cache.exists():
            with np.load(cache, allow_pickle=False) as z:
                prior, bank, rotations, symmetries, center = (
                    z["prior_tokens"], z["template_bank"], z["template_rotations"],
                    z["symmetries"], z["center"])
            self.timings[int(obj_id)] = dict(render=0.0, embed=0.0)
            if progress is not None:
                progress.update(self.views_per_object)
        else:
            prior, bank, rotations, render = self._embed(model, obj_id, progress)
            symmetries, center = bank_symmetries(model.symmetries), render.sphere[0]
            if cache is not None:
                atomic_savez(cache, prior_tokens=prior, template_bank=bank,
                              template_rotations=rotations, symmetries=symmetries, center=center)
        render_mesh = model if model.num_faces <= RENDER_FACES else prepare_mesh(
            model, max_faces=RENDER_FACES)
        return OnboardedObject(int(obj_id), model.name, render_mesh, float(model.diameter),
                               model_points(model.vertices), prior, bank, np.asarray(rotations, np.float32),
                               np.asarray(symmetries, np.float32), np.asarray(center, np.float32))

    def onboard_all(self, meshes: Mapping[int, str | os.PathLike | Mesh], units: str = "mm",
                    show_progress: bool = True) -> list[OnboardedObject]:
        """Onboard every ``{obj_id: mesh}`` with one progress bar: views rendered and embedded
        (``views_per_object`` per object, cached ones at once), ETA, and the current object in
        the postfix."""
        total = len(meshes) * self.views_per_object
        out = []
        with tqdm(total=total, unit="view", desc="onboarding", disable=not show_progress,
                  dynamic_ncols=True) as bar:
            for k, (oid, m) in enumerate(sorted(meshes.items())):
                name = m.name if isinstance(m, Mesh) else pathlib.Path(m).name
                bar.set_postfix_str(f"object {k + 1}/{len(meshes)}: {oid} ({name})")
                out.append(self.onboard(oid, m, units, bar))
        return out
