"""Pose errors against brute-force float64 loops, SciPy rotations and hand-derived values."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from threept_jax.data.bop import load_models
from threept_jax.eval import pose_error as pe
from threept_jax.geometry.symmetry import ContinuousSymmetry, Symmetries, symmetry_transforms

K = np.array([[1075.65, 0.0, 320.5], [0.0, 1073.9, 239.2], [0.0, 0.0, 1.0]])


def _reference_syms(symmetries: Symmetries, step=0.01):
    """Symmetry set built independently with SciPy rotation vectors."""
    disc = [(np.eye(3), np.zeros(3))] + [(m[:3, :3], m[:3, 3]) for m in symmetries.discrete]
    cont = []
    for s in symmetries.continuous:
        n = math.ceil(math.pi / step)
        axis = s.axis / np.linalg.norm(s.axis)
        for i in range(n):
            R = Rotation.from_rotvec(axis * (2 * math.pi * i / n)).as_matrix()
            cont.append((R, s.offset - R @ s.offset))
    if not cont:
        return disc
    return [(Rc @ Rd, Rc @ td + tc) for Rd, td in disc for Rc, tc in cont]


def _brute_mssd(Re, te, Rg, tg, pts, syms):
    best = math.inf
    for Rs, ts in syms:
        worst = 0.0
        for x in pts:
            d = (Re @ x + te) - (Rg @ (Rs @ x + ts) + tg)
            worst = max(worst, math.sqrt(float(d @ d)))
        best = min(best, worst)
    return best


def _brute_mspd(Re, te, Rg, tg, K, pts, syms):
    def proj(X):
        u = K @ X
        return u[:2] / u[2]

    best = math.inf
    for Rs, ts in syms:
        worst = 0.0
        for x in pts:
            d = proj(Re @ x + te) - proj(Rg @ (Rs @ x + ts) + tg)
            worst = max(worst, math.sqrt(float(d @ d)))
        best = min(best, worst)
    return best


def _random_pairs(n, seed, noise_rot=0.15, noise_t=8.0):
    rng = np.random.default_rng(seed)
    Rg = Rotation.random(n, random_state=seed).as_matrix()
    tg = rng.normal(size=(n, 3)) * 60 + [0, 0, 800]
    Re = (
        Rotation.from_matrix(Rg) * Rotation.from_rotvec(rng.normal(size=(n, 3)) * noise_rot)
    ).as_matrix()
    te = tg + rng.normal(size=(n, 3)) * noise_t
    return Re, te, Rg, tg


def test_symmetry_transforms_match_scipy_construction():
    syms = Symmetries(
        discrete=[np.diag([-1.0, -1.0, 1.0, 1.0]), np.diag([1.0, -1.0, -1.0, 1.0])],
        continuous=[ContinuousSymmetry([0, 0, 2.0], [1.0, -2.0, 0.5])],
    )
    R, t = symmetry_transforms(syms)
    ref = _reference_syms(syms)
    assert len(R) == 3 * math.ceil(math.pi / 0.01) == 3 * 315
    np.testing.assert_allclose(R, np.stack([r for r, _ in ref]), atol=1e-12)
    np.testing.assert_allclose(t, np.stack([v for _, v in ref]), atol=1e-12)
    R, t = symmetry_transforms(Symmetries())
    np.testing.assert_array_equal(R, np.eye(3)[None])
    np.testing.assert_array_equal(t, np.zeros((1, 3)))


@pytest.fixture(scope="module")
def tless(bop_models_dir):
    return load_models(bop_models_dir / "tless" / "models")


@pytest.mark.parametrize("obj_id", [4, 27])  # continuous axis symmetry; 3 discrete ones
def test_mssd_mspd_match_brute_force(tless, obj_id):
    model = tless[obj_id]
    pm = pe.prepare_model(model)
    sub = np.random.default_rng(0).choice(len(pm.points), 80, replace=False)
    small = pe.prepare_model(
        points=pm.points[sub], symmetries=model.symmetries, diameter=model.diameter
    )
    syms = _reference_syms(model.symmetries)
    Re, te, Rg, tg = _random_pairs(3, seed=obj_id)
    got_s = pe.mssd_pairs(Re, te, Rg, tg, small)
    got_p = pe.mspd_pairs(Re, te, Rg, tg, K, small)
    for i in range(3):
        assert got_s[i] == pytest.approx(
            _brute_mssd(Re[i], te[i], Rg[i], tg[i], small.points, syms), rel=1e-10
        )
        assert got_p[i] == pytest.approx(
            _brute_mspd(Re[i], te[i], Rg[i], tg[i], K, small.points, syms), rel=1e-10
        )


@pytest.mark.parametrize("obj_id", [4, 27])
def test_full_model_shortcuts_are_exact(tless, obj_id):
    """Hull candidates and symmetry pruning give the same value as every vertex x every
    symmetry (vectorised float64 reference)."""
    pm = pe.prepare_model(tless[obj_id])
    R_s, t_s = symmetry_transforms(tless[obj_id].symmetries)
    Re, te, Rg, tg = _random_pairs(1, seed=10 + obj_id)
    for i in range(1):
        Xe = pm.points @ Re[i].T + te[i]
        Xg = np.einsum("sij,nj->sni", Rg[i] @ R_s, pm.points) + (t_s @ Rg[i].T + tg[i])[:, None]
        ref_s = np.linalg.norm(Xe[None] - Xg, axis=-1).max(1).min()
        ue = Xe @ K.T
        ug = Xg @ K.T
        ref_p = (
            np.linalg.norm(ue[None, :, :2] / ue[None, :, 2:] - ug[..., :2] / ug[..., 2:], axis=-1)
            .max(1)
            .min()
        )
        assert pe.mssd(Re[i], te[i], Rg[i], tg[i], pm) == pytest.approx(ref_s, rel=1e-12)
        assert pe.mspd(Re[i], te[i], Rg[i], tg[i], K, pm) == pytest.approx(ref_p, rel=1e-12)


def test_hand_derived_values():
    pts = np.array([[10.0, 0, 0], [-10, 0, 0], [0, 5, 0], [0, 0, 20]])
    R = np.eye(3)
    t = np.array([0.0, 0, 1000])
    shift = np.array([3.0, 0, 0])
    assert pe.mssd(R, t + shift, R, t, pts) == pytest.approx(3.0, abs=1e-9)
    # A shift along x moves each projection by fx * 3 / z: largest for the vertices at z = 1000.
    assert pe.mspd(R, t + shift, R, t, K, pts) == pytest.approx(K[0, 0] * 3 / 1000, rel=1e-12)
    assert pe.add(R, t + shift, R, t, pts) == pytest.approx(3.0)
    Rz = Rotation.from_euler("z", 180, degrees=True).as_matrix()
    # 180 deg about z: the x-axis points swap, the y point moves by 10, the z point stays.
    assert pe.mssd(Rz, t, R, t, pts) == pytest.approx(20.0)
    sym = Symmetries(discrete=[np.diag([-1.0, -1.0, 1.0, 1.0])])
    assert pe.mssd(Rz, t, R, t, pts, sym) == pytest.approx(0.0, abs=1e-9)
    assert pe.rotation_error_deg(Rz, R) == pytest.approx(180.0)
    assert pe.translation_error(t + shift, t) == pytest.approx(3.0)


def test_add_and_adi_match_brute_force(tless):
    pts = tless[27].vertices()[::40]
    Re, te, Rg, tg = _random_pairs(1, seed=3)
    Xe = pts @ Re[0].T + te[0]
    Xg = pts @ Rg[0].T + tg[0]
    assert pe.add(Re[0], te[0], Rg[0], tg[0], pts) == pytest.approx(
        np.mean([np.linalg.norm(a - b) for a, b in zip(Xe, Xg)]), rel=1e-12
    )
    nn = [min(np.linalg.norm(Xe - g, axis=1)) for g in Xg]
    assert pe.adi(Re[0], te[0], Rg[0], tg[0], pts) == pytest.approx(np.mean(nn), rel=1e-12)
    ang = np.degrees(
        np.linalg.norm(
            (Rotation.from_matrix(Re[0]) * Rotation.from_matrix(Rg[0]).inv()).as_rotvec()
        )
    )
    assert pe.rotation_error_deg(Re[0], Rg[0]) == pytest.approx(ang, rel=1e-9)
