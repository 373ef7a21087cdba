"""Random object queries for detector tests and benchmarks: what onboarding would give a
detector (prior tokens, unit template descriptors, template rotations, model points), drawn
from a generator instead of rendered, for code whose checks do not depend on the values."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from threept_jax.geometry.grids import super_fibonacci_rotations
from threept_jax.models.configs import DetectorConfig
from threept_jax.pipeline.detection import ObjectQueries


def random_queries(cfg: DetectorConfig, num_objects: int, num_templates: int, num_points: int,
                   rng: np.random.Generator) -> ObjectQueries:
    """:class:`ObjectQueries` of ``num_objects`` objects for a detector of ``cfg``: normal
    prior tokens, unit-norm normal descriptors of ``num_templates`` templates at super-Fibonacci
    rotations, ``num_points`` model points (mm, sigma 20) each."""
    bank = rng.normal(size=(num_objects, num_templates, cfg.embed_dim)).astype(np.float32)
    return ObjectQueries(
        jnp.asarray(rng.normal(size=(num_objects, cfg.num_prior_tokens, cfg.width)), jnp.float32),
        jnp.asarray(bank / np.linalg.norm(bank, axis=-1, keepdims=True)),
        jnp.asarray(super_fibonacci_rotations(num_templates), jnp.float32),
        jnp.asarray(rng.normal(0, 20, (num_objects, num_points, 3)), jnp.float32))
