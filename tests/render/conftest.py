"""Fixtures for rendering tests: an independent float64 ray caster and shared test meshes.

Compiled JAX renderers are cached by (face bucket, image size, batch, outputs, tile): each test
module sticks to a few combinations so the suite compiles each once.
"""

import functools
import warnings

import numpy as np
import pytest

BOP_FACES = 1500  # BOP meshes are decimated to at most this many faces for tests


def raycast_reference(vertices, faces, T_cam_obj, K, hw, near=1.0):
    """Brute-force float64 ray casting (Moller-Trumbore over every pixel x face).

    Returns depth [H, W] (z, 0 = background) and face [H, W] (-1 = background) for one view.
    """
    H, W = hw
    T = np.asarray(T_cam_obj, np.float64)
    X = np.asarray(vertices, np.float64) @ T[:3, :3].T + T[:3, 3]
    tri = X[np.asarray(faces)]  # [F, 3, 3]
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    pix = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3)
    d = pix @ np.linalg.inv(np.asarray(K, np.float64)).T  # [P, 3], z = 1 so t = depth
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    pvec = np.cross(d[:, None, :], e2[None])  # [P, F, 3]
    det = np.einsum("fi,pfi->pf", e1, pvec)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tvec = -v0  # ray origin (camera centre) minus v0
    a = np.einsum("fi,pfi->pf", tvec, pvec) * inv
    qvec = np.cross(tvec, e1)  # [F, 3]
    b = np.einsum("pi,fi->pf", d, qvec) * inv
    t = np.einsum("fi,fi->f", e2, qvec)[None] * inv
    hit = ok & (a >= 0) & (b >= 0) & (a + b <= 1) & (t > near)
    z = np.where(hit, t, np.inf)
    face = np.argmin(z, axis=1)
    depth = z[np.arange(len(z)), face]
    bg = ~np.isfinite(depth)
    return (
        np.where(bg, 0.0, depth).reshape(H, W),
        np.where(bg, -1, face).reshape(H, W),
    )


@pytest.fixture(scope="session")
def raycast():
    return raycast_reference


@pytest.fixture(scope="session")
def bop_mesh(bop_models_dir):
    """Loader of prepared shared BOP meshes: bop_mesh(dataset, obj_id) -> Mesh (<= 1500 faces)."""
    from threept_jax.render import load_mesh, prepare_mesh

    @functools.lru_cache(maxsize=None)
    def load(dataset, obj_id, max_faces=BOP_FACES):
        path = bop_models_dir / dataset / "models" / f"obj_{obj_id:06d}.ply"
        if not path.is_file():
            pytest.skip(f"{path} not found")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return prepare_mesh(load_mesh(path), max_faces=max_faces)

    return load


def look_at_poses(mesh, rotations, distance_factor=2.5):
    """T_cam_obj [B, 4, 4]: rotations [B, 3, 3] about the mesh centre, which sits on the optical
    axis at distance_factor x diameter."""
    R = np.asarray(rotations, np.float64)
    T = np.tile(np.eye(4), (len(R), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = -R @ mesh.center.astype(np.float64) + [0, 0, distance_factor * mesh.diameter]
    return T


def random_rotations(n, seed):
    from scipy.spatial.transform import Rotation

    return Rotation.random(n, random_state=seed).as_matrix()


@pytest.fixture(scope="session")
def poses():
    """poses(mesh, n, seed, distance_factor=2.5) -> T_cam_obj [n, 4, 4] at random rotations."""
    return lambda mesh, n, seed, distance_factor=2.5: look_at_poses(
        mesh, random_rotations(n, seed), distance_factor
    )
