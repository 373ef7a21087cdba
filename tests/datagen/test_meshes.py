"""Mesh pool: discovery, obj_id assignment, BOP metadata, units, skip-with-warning on bad files.

References: ``models_info.json`` read directly with ``json``, brute-force diameters with SciPy
``pdist``, and the exact geometry written by the tests themselves.
"""

import json
import warnings

import numpy as np
import pytest
import trimesh
from scipy.spatial.distance import pdist

from datagen import meshes as M
from datagen import procedural as P


@pytest.fixture()
def plain_tree(tmp_path):
    """A tree of meshes in several formats, one corrupt file, one truncated, one in metres."""
    root = tmp_path / "cad"
    (root / "sub").mkdir(parents=True)
    box = trimesh.creation.box(extents=(10.0, 20.0, 30.0))
    box.apply_translation((5.0, 7.0, 9.0))  # off-centre: the pool must recentre it
    box.export(root / "sub" / "box.obj")
    cyl = trimesh.creation.cylinder(radius=15.0, height=40.0, sections=32)
    cyl.export(root / "cyl.ply")
    cyl.export(root / "cyl_copy.glb")
    (root / "garbage.ply").write_bytes(np.random.default_rng(0).bytes(3000))
    (root / "truncated.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n"
    )
    trimesh.creation.box(extents=(0.1, 0.2, 0.05)).export(root / "in_metres.stl")
    (root / "readme.txt").write_text("not a mesh")
    return root


def test_plain_tree_ids_follow_sorted_relative_paths(plain_tree):
    pool = M.build_pool([plain_tree])
    names = [r.name for r in pool.records]
    assert names == [
        "cad/cyl",
        "cad/cyl_copy",
        "cad/garbage",
        "cad/in_metres",
        "cad/sub/box",
        "cad/truncated",
    ]
    assert [r.obj_id for r in pool.records] == [1, 2, 3, 4, 5, 6]
    assert all(r.diameter is None and r.mesh is None for r in pool.records)


def test_bad_meshes_are_skipped_with_a_warning_and_counted(plain_tree):
    pool = M.build_pool([plain_tree])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        loaded = pool.load_all()
    messages = [str(w.message) for w in caught if issubclass(w.category, M.MeshSkippedWarning)]
    assert len(messages) == 3
    assert any("garbage.ply" in m for m in messages)
    assert any("truncated.ply" in m and "the file is truncated" in m for m in messages)
    assert any("in_metres.stl" in m and "metres" in m and "units='m'" in m for m in messages)
    assert pool.skipped == 3
    assert set(pool.skipped_reasons) == {"cad/garbage", "cad/truncated", "cad/in_metres"}
    assert [m.record.name for m in loaded] == ["cad/cyl", "cad/cyl_copy", "cad/sub/box"]
    # A skipped mesh stays skipped, silently and without being counted twice.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert pool.load(2) is None
    assert pool.skipped == 3


def test_plain_meshes_are_recentred_and_keep_their_size(plain_tree):
    pool = M.build_pool([plain_tree])
    box = pool.load(4)
    np.testing.assert_allclose(box.mesh.bounds, [[-5, -10, -15], [5, 10, 15]], atol=1e-9)
    assert box.diameter == pytest.approx(np.sqrt(10**2 + 20**2 + 30**2))
    info = box.models_info()
    assert info["min_x"] == pytest.approx(-5) and info["size_z"] == pytest.approx(30)
    cyl, glb = pool.load(0), pool.load(1)
    np.testing.assert_allclose(
        np.sort(glb.mesh.vertices, 0), np.sort(cyl.mesh.vertices, 0), atol=1e-5
    )
    assert cyl.diameter == pytest.approx(pdist(cyl.mesh.vertices).max())


def test_declared_units_convert_to_millimetres(plain_tree):
    pool = M.build_pool([M.MeshFolder(plain_tree, units="m")])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        metres = pool.load(3)
    np.testing.assert_allclose(metres.mesh.extents, [100.0, 200.0, 50.0], rtol=1e-6)  # STL: float32
    with pytest.raises(ValueError, match="unknown units"):
        M.build_pool([M.MeshFolder(plain_tree, units="furlong")])


def test_bop_folder_keeps_ids_diameters_and_symmetries(bop_models_dir):
    folder = bop_models_dir / "itodd" / "models"
    info = {int(k): v for k, v in json.loads((folder / "models_info.json").read_text()).items()}
    files = sorted(int(p.stem.split("_")[1]) for p in folder.glob("obj_*.ply"))
    pool = M.build_pool([folder], first_obj_id=101)
    assert [r.source_obj_id for r in pool.records] == files
    assert [r.obj_id for r in pool.records] == list(range(101, 101 + len(files)))
    for r in pool.records:
        assert r.name == f"itodd/obj_{r.source_obj_id:06d}"
        assert r.diameter == pytest.approx(info[r.source_obj_id]["diameter"])
        expected = np.array(info[r.source_obj_id].get("symmetries_discrete", []), np.float64)
        np.testing.assert_array_equal(
            np.array(r.symmetries.discrete).reshape(expected.shape), expected
        )
        assert len(r.symmetries.continuous) == len(
            info[r.source_obj_id].get("symmetries_continuous", [])
        )
    # The smallest file: the loaded mesh agrees with models_info and with brute force.
    k = files.index(3)
    mesh = pool.load(k)
    assert mesh.diameter == pytest.approx(pdist(mesh.mesh.vertices).max(), rel=1e-12)
    assert mesh.diameter == pytest.approx(info[3]["diameter"], rel=1e-3)
    for axis in "xyz":
        assert mesh.models_info()[f"min_{axis}"] == pytest.approx(info[3][f"min_{axis}"], abs=1e-3)
    assert mesh.models_info()["symmetries_discrete"] == [
        list(s) for s in info[3]["symmetries_discrete"]
    ]


def test_continuous_symmetries_and_folder_order(bop_models_dir):
    tless = bop_models_dir / "tless" / "models"
    itodd = bop_models_dir / "itodd" / "models"
    pool = M.build_pool([tless, itodd])
    n_tless = len(list(tless.glob("obj_*.ply")))
    assert all(r.name.startswith("tless/") for r in pool.records[:n_tless])
    assert all(r.name.startswith("itodd/") for r in pool.records[n_tless:])
    info = json.loads((tless / "models_info.json").read_text())
    rec = pool.records[0]
    cont = info[str(rec.source_obj_id)].get("symmetries_continuous", [])
    assert [{"axis": c.axis.tolist(), "offset": c.offset.tolist()}
            for c in rec.symmetries.continuous] == [
        {"axis": [float(x) for x in c["axis"]], "offset": [float(x) for x in c["offset"]]}
        for c in cont
    ]


def test_procedural_parts_join_the_pool_after_folders(plain_tree):
    parts = P.generate_parts(np.random.default_rng(0), 3, families=["washer", "nut"])
    pool = M.build_pool([plain_tree], parts)
    recs = pool.records[-3:]
    assert [r.obj_id for r in recs] == [7, 8, 9]
    assert all(r.source == "procedural" and r.path is None for r in recs)
    for r, part in zip(recs, parts):
        assert r.name.startswith(f"procedural/{part.family}_")
        loaded = pool.load(r.obj_id - 1)
        assert loaded.mesh is part.mesh
        assert loaded.diameter == pytest.approx(part.diameter)
        info = loaded.models_info()
        assert info["symmetries_discrete"] == part.symmetries.to_json()["symmetries_discrete"]


def test_sample_draws_distinct_usable_meshes_deterministically(plain_tree):
    pool = M.build_pool([plain_tree])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", M.MeshSkippedWarning)
        a = pool.sample(np.random.default_rng(3), 3)
        b = M.build_pool([plain_tree]).sample(np.random.default_rng(3), 3)
        c = pool.sample(np.random.default_rng(3), 10)
    assert a == b
    assert sorted(a) == [0, 1, 4], "exactly the three usable meshes"
    assert sorted(c) == [0, 1, 4], "never more than the usable ones"


def test_configuration_errors_raise_with_the_fix(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        M.build_pool([tmp_path / "nope"])
    (tmp_path / "empty").mkdir()
    with (
        pytest.warns(UserWarning, match="no meshes"),
        pytest.raises(ValueError, match="no meshes found"),
    ):
        M.build_pool([tmp_path / "empty"])
    bop = tmp_path / "bop" / "models"
    bop.mkdir(parents=True)
    (bop / "models_info.json").write_text("{not json")
    with pytest.raises(ValueError, match="models_info.json"):
        M.build_pool([bop])


def test_units_message_names_the_flag_of_the_cli(plain_tree):
    from datagen.generate import build_pool

    pool = build_pool([str(plain_tree)], seed=0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        pool.load_all()
    reason = pool.skipped_reasons["cad/in_metres"]
    assert "in_metres.stl" in reason and "--mesh-units m" in reason and "units='" not in reason
    msgs = [str(w.message) for w in caught if "in_metres" in str(w.message)]
    assert len(msgs) == 1 and msgs[0].count("in_metres.stl") == 1
