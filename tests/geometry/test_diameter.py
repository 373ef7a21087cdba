"""Mesh diameter: exact against brute-force float64 pairwise distances, the stated bound for
round meshes, bounded memory on a 2M-face mesh, and the units error."""

import subprocess
import sys
import textwrap

import numpy as np
import pytest
from scipy.spatial.distance import pdist

from tests.fixtures.training import SUBPROCESS_ENV
from threept_jax.geometry.diameter import (
    DIAMETER_RTOL,
    EXACT_MAX_CANDIDATES,
    MeshUnitsError,
    check_units,
    diameter_bounds,
    mesh_diameter,
)


@pytest.mark.parametrize("seed", range(6))
def test_exact_on_random_point_sets(seed):
    # Sizes above the brute-force threshold, so the pruning passes run; anisotropic, offset,
    # flat and rounded (tied) sets.
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1500, 4000))
    v = rng.normal(size=(n, 3)) * rng.uniform(0.5, 100, size=3) + rng.normal(size=3) * 1e4
    if seed % 3 == 0:
        v[:, 2] = 7.0  # planar
    if seed % 2 == 0:
        v = np.round(v)  # many equal distances
    lo, hi = diameter_bounds(v)
    want = pdist(v).max()
    assert lo == hi
    np.testing.assert_allclose(lo, want, rtol=1e-13)


def test_exact_on_a_dense_cylinder_rim():
    # Every rim vertex has an antipode: many candidates, still few enough to be exact.
    t = np.linspace(0, 2 * np.pi, 3000, endpoint=False)
    rim = np.stack([40 * np.cos(t), 40 * np.sin(t), np.zeros_like(t)], 1)
    v = np.concatenate([rim, rim + [0, 0, 30], np.random.default_rng(0).uniform(-20, 20, (5000, 3))])
    lo, hi = diameter_bounds(v)
    assert lo == hi
    np.testing.assert_allclose(lo, pdist(v).max(), rtol=1e-13)


def test_round_meshes_beyond_the_exact_budget_stay_within_the_stated_bound():
    # 20k points on a sphere of radius 50 plus one antipodal pair: every point can end a
    # near-diametral pair, so the result is a bound; the true diameter is 100 (no two points
    # of the sphere are farther apart than its diameter, and the pair reaches it).
    rng = np.random.default_rng(3)
    v = rng.normal(size=(20_000, 3))
    v = np.concatenate([[[0, 0, 50.0], [0, 0, -50.0]], 50 * v / np.linalg.norm(v, axis=1)[:, None]])
    assert len(v) > EXACT_MAX_CANDIDATES
    lo, hi = diameter_bounds(v)
    assert lo <= 100.0 * (1 + 1e-12) and 100.0 <= hi * (1 + 1e-12)
    assert hi <= lo * (1 + DIAMETER_RTOL) * (1 + 1e-12)
    assert (100.0 - lo) / 100.0 <= DIAMETER_RTOL < 2e-3


def test_degenerate_inputs():
    assert mesh_diameter(np.zeros((1, 3))) == 0.0
    assert mesh_diameter(np.zeros((5000, 3))) == 0.0
    with pytest.raises(ValueError, match="NaN or inf"):
        mesh_diameter(np.array([[0, 0, 0], [np.nan, 0, 0]]))


def test_units_error_carries_the_measurement_and_rephrases_for_a_cli():
    with pytest.raises(MeshUnitsError) as err:
        check_units(0.25, "part.ply")
    e = err.value
    assert isinstance(e, ValueError) and e.diameter == 0.25 and e.path == "part.ply"
    assert "part.ply" in str(e) and "units='m'" in str(e)
    assert "--mesh-units m" in e.message("--mesh-units {}") and "units='" not in e.message(
        "--mesh-units {}")
    assert "micrometres" in str(pytest.raises(MeshUnitsError, check_units, 9000.0, "x").value)
    assert check_units(120.0, "x") == 120.0


def test_a_two_million_face_mesh_loads_in_bounded_memory(tmp_path):
    # A UV sphere of 1999392 faces (999698 vertices, all on the hull: the worst case of the
    # old exact method, which needed hours and terabytes). Peak RSS is measured in a fresh
    # process, against the same process's RSS after its imports.
    import trimesh

    path = tmp_path / "sphere.ply"
    trimesh.creation.uv_sphere(radius=50.0, count=[708, 708]).export(path)
    code = textwrap.dedent(f"""
        import resource, warnings
        from threept_jax.render.mesh import load_mesh
        base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            m = load_mesh({str(path)!r})
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        print(m.num_faces, m.diameter, (peak - base) / 1024)
    """)
    out = subprocess.run([sys.executable, "-c", code], env=SUBPROCESS_ENV, capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    faces, diameter, extra_mb = out.stdout.split()
    assert int(faces) == 1999392
    assert 100.0 * (1 - DIAMETER_RTOL) <= float(diameter) <= 100.0 * (1 + 1e-6)  # float32 file
    assert float(extra_mb) < 2048, f"loading took {extra_mb} MB above the imports"
