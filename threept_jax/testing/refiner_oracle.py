"""An oracle refiner network for tests: descriptors from ground-truth object coordinates.

The oracle stands in for the 3PT-R network (``threept_jax.models.refiner``, the refiner contract
of issue 14) wherever a test needs correct descriptors without a trained model: the refinement
step's convergence tests and the refiner trainer's tests.

How it sees object coordinates: :func:`xyz_colored` paints a mesh with its own normalised
object coordinates as vertex colours. Rendered with ``ambient=1`` (no shading), a pixel's
colour is then exactly the normalised object coordinate of the surface point it sees
(barycentric interpolation of a linear function is exact). The real crops of a test are that
mesh rendered at the ground-truth pose, and the step renders the same mesh at the hypotheses,
so the oracle reads ground-truth coordinates off the real crops and hypothesis coordinates off
the renders, as a pure function of the images (no captured state: one jit trace serves every
scene).

Descriptors: (orthogonal) random Fourier features of the normalised coordinate c [3],
``e(c) = (cos(c W), sin(c W)) / sqrt(D)`` with W [3, D] ~ N(0, 1 / sigma^2), a unit vector whose
dot products ``e(a) . e(b) = mean_d cos((a - b) . w_d)`` approximate the Gaussian kernel
``exp(-|a - b|^2 / (2 sigma^2))``: a peaked kernel of 3D distance, exactly 1 at a = b and
quadratic near it. Background pixels get one extra axis, orthogonal to every object descriptor.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from threept_jax.render.mesh import Mesh

COLOR_SCALE = 2.2  # colour = 0.5 + (x - center) / (COLOR_SCALE * radius): in [0.05, 0.95]


def xyz_colored(mesh: Mesh) -> Mesh:
    """The mesh with vertex colours 0.5 + (x - center) / (2.2 radius), one scale for all axes."""
    c = 0.5 + (mesh.vertices - mesh.center) / (COLOR_SCALE * mesh.radius)
    return mesh.replace(colors=c.astype(np.float32), uv=None, texture=None)


def _pool(img: jax.Array, size: int):
    """[..., H, W, 3] colours -> ([..., h, w, 3] block means, [..., h, w] all-object blocks).

    Block means sit at the map's pixel centres ((j + 0.5) H / h - 0.5), the contract's rule.
    """
    H = img.shape[-2]
    if H % size:
        raise ValueError(f"oracle: crop size {H} must be a multiple of the map size {size}")
    s = H // size
    blocks = img.reshape(img.shape[:-3] + (size, s, size, s, 3))
    fg = jnp.all(jnp.sum(blocks, -1) > 0, axis=(-3, -1))
    return jnp.mean(blocks, axis=(-4, -2)), fg


def make_oracle(output_size: int, *, sigma: float = 0.35, num_features: int = 192,
                noise: float = 0.0, outliers: float = 0.0, seed: int = 0):
    """An oracle ``network(real [1, V, H, W, 3], renders [1, K, V, H, W, 3]) -> dict``.

    Follows the refiner contract's outputs at map size h = ``output_size`` (H a multiple of h):
    ``real_desc``, ``render_desc`` [1, K, V, h, w, 2 D + 1] (module docstring; a map pixel is
    object only if its whole H / h block is), ``mask_logits`` (+10 on the real crop's object,
    -10 elsewhere), ``view_scores`` (10 x IoU of the real and rendered object masks) and
    ``scores`` (their mean over views). Images are float colours of :func:`xyz_colored` meshes.

    Args:
      sigma: kernel width in normalised coordinates (1 = 2.2 bounding-sphere radii).
      noise: standard deviation of Gaussian noise added to every descriptor component times
        sqrt(2 D + 1) (so ``noise`` is the noise-to-signal norm ratio) before renormalising;
        a fixed pattern per pixel drawn from ``seed``, different for real and render maps.
      outliers: share of the real map's object pixels whose descriptor is that of another,
        random point of the object's bounding box (a fixed pattern per pixel drawn from
        ``seed``): wrong matches, as a network makes on a part it does not know.
        ``noise`` and ``outliers`` may be traced (an oracle made inside ``jit``).

    Create one oracle and reuse it: jit caches the step per network function object.
    """
    if num_features % 3:
        raise ValueError(f"oracle: num_features must be a multiple of 3, got {num_features}")
    concrete = isinstance(noise, (int, float)) and isinstance(outliers, (int, float))
    if concrete and (not 0.0 <= outliers <= 1.0 or not noise >= 0.0):
        raise ValueError(f"oracle: outliers must be in [0, 1] and noise >= 0, got {outliers} "
                         f"and {noise}")
    # Traced levels (an oracle made inside a jitted function, one compilation for a whole
    # ladder of levels) always take the noisy path; Python zeros skip it.
    noisy = not concrete or noise > 0
    wrong_share = not concrete or outliers > 0
    key_w, key_n, key_real, key_render, key_out = jax.random.split(jax.random.key(seed), 5)
    # Orthogonal random features: triples of orthogonal directions, one chi(3) radius per
    # triple. Each triple adds rho^2 I to sum w w^T, so the kernel's curvature at 0 is exactly
    # isotropic (plain Gaussian frequencies leave ~sqrt(2 / D) of anisotropy).
    m = num_features // 3
    Q, _ = jnp.linalg.qr(jax.random.normal(key_w, (m, 3, 3)))
    rho = jnp.linalg.norm(jax.random.normal(key_n, (m, 3)), axis=-1)
    W = jnp.transpose(Q * rho[:, None, None], (1, 0, 2)).reshape(3, num_features) / sigma
    C = 2 * num_features + 1

    def embed(color, fg, key):
        ang = color @ W
        e = jnp.concatenate([jnp.cos(ang), jnp.sin(ang), jnp.zeros(ang.shape[:-1] + (1,))], -1)
        e = e / np.sqrt(num_features)
        bg = jnp.zeros((C,)).at[-1].set(1.0)
        e = jnp.where(fg[..., None], e, bg)
        if noisy:
            e = e + noise / np.sqrt(C) * jax.random.normal(key, e.shape)
            e = e / jnp.linalg.norm(e, axis=-1, keepdims=True)
        return e

    def network(real, renders):
        real = jnp.asarray(real, jnp.float32)
        renders = jnp.asarray(renders, jnp.float32)
        K = renders.shape[1]
        real_c, real_fg = _pool(real, output_size)  # [1, V, h, w, 3]
        if wrong_share:
            k_pick, k_where = jax.random.split(key_out)
            wrong = jax.random.uniform(k_where, real_c.shape[:-1]) < outliers
            other = jax.random.uniform(k_pick, real_c.shape, minval=0.05, maxval=0.95)
            real_c = jnp.where(wrong[..., None], other, real_c)
        rend_c, rend_fg = _pool(renders, output_size)  # [1, K, V, h, w, 3]
        F = embed(real_c, real_fg, key_real)
        Z = embed(rend_c, rend_fg, key_render)
        F = jnp.broadcast_to(F[:, None], F.shape[:1] + (K,) + F.shape[1:])
        real_fg = jnp.broadcast_to(real_fg[:, None], rend_fg.shape)
        inter = jnp.sum(real_fg & rend_fg, axis=(-2, -1))
        union = jnp.sum(real_fg | rend_fg, axis=(-2, -1))
        view_scores = 10.0 * inter / jnp.maximum(union, 1)
        return {
            "real_desc": F,
            "render_desc": Z,
            "mask_logits": jnp.where(real_fg, 10.0, -10.0),
            "view_scores": view_scores,
            "scores": jnp.mean(view_scores, -1),
        }

    return network
