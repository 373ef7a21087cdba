"""Mesh loading, unit checks, decimation, subdivision and padding."""

import json
import warnings

import numpy as np
import pytest
import trimesh

from threept_jax.geometry.diameter import mesh_diameter
from threept_jax.render import Mesh, bucket_size, decimate, load_mesh, subdivide, to_raster_mesh
from threept_jax.render.mesh import is_closed


def _write_ply(path, vertices, faces, colors=None):
    lines = ["ply", "format ascii 1.0", f"element vertex {len(vertices)}",
             "property float x", "property float y", "property float z"]
    if colors is not None:
        lines += ["property uchar red", "property uchar green", "property uchar blue"]
    lines += [f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    for i, v in enumerate(vertices):
        extra = "" if colors is None else " " + " ".join(str(int(c)) for c in colors[i])
        lines.append(" ".join(f"{x:.6f}" for x in v) + extra)
    lines += ["3 " + " ".join(str(int(i)) for i in f) for f in faces]
    path.write_text("\n".join(lines) + "\n")
    return path


def _box(extents):
    b = trimesh.creation.box(extents=extents)
    return np.asarray(b.vertices), np.asarray(b.faces)


def test_units_are_checked_never_rescaled_silently(tmp_path):
    v, f = _box((0.1, 0.05, 0.02))  # a 10 cm part stored in metres
    path = _write_ply(tmp_path / "part.ply", v, f)
    with pytest.raises(ValueError, match="units='m'"):
        load_mesh(path)
    mesh = load_mesh(path, units="m")
    np.testing.assert_allclose(mesh.diameter, 1000 * np.linalg.norm([0.1, 0.05, 0.02]), rtol=1e-6)
    np.testing.assert_allclose(mesh.vertices, 1000 * v, atol=1e-3)
    big = _write_ply(tmp_path / "big.ply", *_box((9000.0, 10.0, 10.0)))
    with pytest.raises(ValueError, match="units="):
        load_mesh(big)
    with pytest.raises(ValueError, match="units must be one of"):
        load_mesh(path, units="furlong")


def test_empty_and_broken_meshes(tmp_path):
    with pytest.raises(ValueError, match="empty"):
        Mesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), int))
    with pytest.raises(ValueError, match="face indices"):
        Mesh(vertices=np.eye(3) * 10, faces=[[0, 1, 3]])
    empty = tmp_path / "empty.ply"
    empty.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                     "property float z\nelement face 0\nproperty list uchar int vertex_indices\n"
                     "end_header\n0 0 0\n10 0 0\n0 10 0\n")
    with pytest.raises(ValueError):
        load_mesh(empty)
    with pytest.raises(FileNotFoundError):
        load_mesh(tmp_path / "missing.ply")


def test_open_degenerate_and_duplicate_faces_warn(tmp_path):
    v, f = _box((40.0, 30.0, 20.0))
    with pytest.warns(UserWarning, match="not watertight"):
        load_mesh(_write_ply(tmp_path / "open.ply", v, f[:-1]))
    v2 = np.concatenate([v, [[5.0, 5.0, 5.0]]])
    f2 = np.concatenate([f, [[8, 8, 8]]])  # a zero-area face
    with pytest.warns(UserWarning) as record:
        load_mesh(_write_ply(tmp_path / "degen.ply", v2, f2))
    assert any("1 of 13 faces are degenerate" in str(w.message) for w in record)
    # The surface written twice (vertices and faces repeated): the copy is dropped.
    v3, f3 = np.concatenate([v, v]), np.concatenate([f, f + len(v)])
    with pytest.warns(UserWarning, match="dropped 12 of 24 faces"):
        mesh = load_mesh(_write_ply(tmp_path / "twice.ply", v3, f3))
    assert mesh.num_faces == 12 and mesh.num_vertices == 8 and is_closed(mesh)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        closed = load_mesh(_write_ply(tmp_path / "closed.ply", v, f))
    assert closed.num_faces == 12


def test_bop_mesh_colours_texture_and_models_info(bop_models_dir):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tudl = load_mesh(bop_models_dir / "tudl" / "models" / "obj_000003.ply")
        banana = load_mesh(bop_models_dir / "ycbv" / "models" / "obj_000010.ply")
        tless = load_mesh(bop_models_dir / "tless" / "models" / "obj_000004.ply")
    # Vertex colours, against the ASCII file read line by line.
    lines = (bop_models_dir / "tudl" / "models" / "obj_000003.ply").read_text().splitlines()
    start = lines.index("end_header") + 1
    raw = np.array([[float(x) for x in ln.split()] for ln in lines[start : start + 200]])
    for row in raw[:20]:
        k = np.argmin(np.linalg.norm(tudl.vertices - row[:3], axis=1))
        np.testing.assert_allclose(tudl.vertices[k], row[:3], atol=1e-4)
        np.testing.assert_allclose(tudl.colors[k], row[6:9] / 255.0, atol=1e-6)
    assert banana.texture is not None and banana.texture.shape == (4096, 4096, 3)
    assert banana.uv.shape == (banana.num_vertices, 2) and banana.colors is None
    assert 0 <= banana.uv.min() and banana.uv.max() <= 1
    info = json.loads((bop_models_dir / "tless" / "models" / "models_info.json").read_text())["4"]
    np.testing.assert_allclose(tless.diameter, info["diameter"], rtol=2e-3)
    assert len(tless.symmetries.continuous) == len(info.get("symmetries_continuous", []))
    np.testing.assert_allclose(
        tless.symmetries.discrete,
        np.asarray(info.get("symmetries_discrete", []), np.float32).reshape(-1, 4, 4))
    # Unit vertex normals even where the file stores unnormalised ones (YCB-V obj 10).
    np.testing.assert_allclose(np.linalg.norm(banana.normals, axis=1), 1, atol=1e-5)


def test_diameter_is_max_vertex_distance():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(300, 3)) * [40, 20, 10]
    brute = np.max(np.linalg.norm(pts[:, None] - pts[None], axis=-1))
    np.testing.assert_allclose(mesh_diameter(pts), brute, rtol=1e-12)


def _sphere(colors=False, uv=False):
    s = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    v = np.asarray(s.vertices)
    M = np.array([[3e-3, 0, 1e-3], [0, 3e-3, 0], [2e-3, 0, -3e-3]])
    lin = lambda p: 0.5 + p @ M  # noqa: E731
    kw = {}
    if colors:
        kw["colors"] = lin(v)
    if uv:
        kw["uv"] = 0.5 + v[:, :2] / 200.0
        kw["texture"] = np.zeros((4, 4, 3), np.uint8)
    return Mesh(vertices=v, faces=s.faces, name="sphere", **kw), lin


def test_decimate_keeps_shape_and_attributes():
    mesh, lin = _sphere(colors=True)
    small = decimate(mesh, 500)
    assert 400 <= small.num_faces <= 500
    # Every decimated vertex lies near the original surface (radius 50).
    np.testing.assert_allclose(np.linalg.norm(small.vertices, axis=1), 50, atol=1.0)
    # Colours follow the (linear) colour field: taken from the nearest original vertex.
    np.testing.assert_allclose(small.colors, np.clip(lin(small.vertices), 0, 1), atol=0.03)
    textured, _ = _sphere(uv=True)
    tsmall = decimate(textured, 500)
    # Per-corner UVs from the nearest original face's chart: here u, v = 0.5 + (x, y) / 200.
    np.testing.assert_allclose(tsmall.uv, 0.5 + tsmall.vertices[:, :2] / 200.0, atol=5e-3)
    assert decimate(mesh, 10**6) is mesh


def test_subdivide_bounds_edges_conformingly():
    v, f = _box((80.0, 40.0, 20.0))
    lin = lambda p: 0.2 + 0.004 * p + 0.001 * p[:, ::-1]  # noqa: E731
    box = Mesh(vertices=v, faces=f, colors=np.clip(lin(v), 0, 1), name="box")
    assert is_closed(box)
    fine = subdivide(box, 7.5)
    corners = fine.vertices[fine.faces]
    edges = np.linalg.norm(corners - np.roll(corners, -1, 1), axis=-1)
    assert edges.max() <= 7.5
    # Conforming (no T-junctions): still closed and consistently wound; same surface and area.
    assert is_closed(fine)
    area = lambda m: 0.5 * np.linalg.norm(np.cross(  # noqa: E731
        m.vertices[m.faces[:, 1]] - m.vertices[m.faces[:, 0]],
        m.vertices[m.faces[:, 2]] - m.vertices[m.faces[:, 0]]), axis=1).sum()
    np.testing.assert_allclose(area(fine), 2 * (80 * 40 + 80 * 20 + 40 * 20), rtol=1e-6)
    assert np.all(np.isclose(np.abs(fine.vertices), [40, 20, 10]).any(axis=1))
    # Linear attributes are reproduced exactly at midpoints.
    np.testing.assert_allclose(fine.colors, np.clip(lin(fine.vertices), 0, 1), atol=1e-5)


def test_buckets_and_padding_share_compiled_renderers():
    sizes = [1, 255, 256, 257, 384, 385, 1000, 1537, 5000, 70000]
    for n in sizes:
        b = bucket_size(n)
        assert b >= n and b >= 256
        assert b == 256 or b <= 1.5 * n + 1
    ladder = [bucket_size(n) for n in (256, 300, 400, 600, 800, 1100)]
    assert ladder == [256, 384, 512, 768, 1024, 1536]
    a = Mesh(vertices=trimesh.creation.icosphere(2, 30.0).vertices,
             faces=trimesh.creation.icosphere(2, 30.0).faces)
    b = Mesh(vertices=trimesh.creation.torus(30.0, 10.0).vertices,
             faces=trimesh.creation.torus(30.0, 10.0).faces)
    ra, rb = to_raster_mesh(a, face_bucket=2048), to_raster_mesh(b, face_bucket=2048)
    assert ra.face_geom.shape == rb.face_geom.shape == (2048, 18)
    assert int(ra.face_mask.sum()) == a.num_faces and int(rb.face_mask.sum()) == b.num_faces
    import jax

    sa = jax.tree_util.tree_structure(ra)
    assert sa == jax.tree_util.tree_structure(rb)
    assert [x.shape for x in jax.tree.leaves(ra)] == [x.shape for x in jax.tree.leaves(rb)]
    with pytest.raises(ValueError, match="face_bucket"):
        to_raster_mesh(b, face_bucket=100)


@pytest.mark.parametrize("ext", ["obj", "stl", "glb", "ply"])
def test_formats_load_to_the_same_geometry(tmp_path, ext):
    box = trimesh.creation.box(extents=(40.0, 30.0, 20.0))
    path = tmp_path / f"box.{ext}"
    box.export(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # STL and OBJ may split vertices per face
        mesh = load_mesh(path, models_info=None)
    np.testing.assert_allclose(mesh.diameter, np.linalg.norm([40, 30, 20]), rtol=1e-6)
    area = 0.5 * np.linalg.norm(np.cross(
        mesh.vertices[mesh.faces[:, 1]] - mesh.vertices[mesh.faces[:, 0]],
        mesh.vertices[mesh.faces[:, 2]] - mesh.vertices[mesh.faces[:, 0]]), axis=1).sum()
    np.testing.assert_allclose(area, 2 * (40 * 30 + 40 * 20 + 30 * 20), rtol=1e-6)
    assert is_closed(mesh)


@pytest.mark.parametrize(
    "body, why",
    [
        (b"", "cannot read the mesh"),
        (np.random.default_rng(1).bytes(2000), "cannot read the mesh"),
        (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
         b"property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
         b"end_header\n0 0 0\n10 0 0\n", "truncated"),
        (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
         b"property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
         b"end_header\n0 0 0\n10 0 0\n0 10 0\n3 0 1 5\n", "face indices out of range"),
        (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
         b"property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
         b"end_header\n0 0 0\nnan 0 0\n0 10 0\n3 0 1 2\n", "NaN or infinite"),
    ],
    ids=["empty", "random", "truncated", "index", "nan"],
)
def test_corrupt_files_name_the_file_and_the_problem(tmp_path, body, why):
    path = tmp_path / "broken.ply"
    path.write_bytes(body)
    with pytest.raises(ValueError, match=why) as err:
        load_mesh(path)
    assert str(path) in str(err.value)


def test_units_error_is_a_dedicated_type_naming_the_file(tmp_path):
    from threept_jax.geometry.diameter import MeshUnitsError

    path = _write_ply(tmp_path / "part.ply", *_box((0.1, 0.05, 0.02)))
    with pytest.raises(MeshUnitsError) as err:
        load_mesh(path)
    assert err.value.path == path
    np.testing.assert_allclose(err.value.diameter, np.linalg.norm([0.1, 0.05, 0.02]), rtol=1e-6)
    assert "--units m" in err.value.message("--units {}")
