"""The PLY reader on corrupt files: every case raises ValueError naming the file and the
problem (no traceback from inside numpy), and a valid file still reads exactly."""

import numpy as np
import pytest
import trimesh

from threept_jax.data.ply import check_ply_counts, load_ply_mesh, load_ply_vertices

HEAD = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n")


def _binary(tmp_path):
    tm = trimesh.Trimesh([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]],
                         [[0, 1, 2], [0, 2, 3]], process=False)
    data = trimesh.exchange.ply.export_ply(tm, encoding="binary")
    return data


CASES = {
    "empty": (b"", "not a PLY file"),
    "random bytes": (np.random.default_rng(0).bytes(3000), "not a PLY file"),
    "no end_header": (b"ply\nformat ascii 1.0\nelement vertex 3\n", "no 'end_header'"),
    "ascii truncated": ((HEAD + "0 0 0\n1 0 0\n").encode(), "ends inside element 'vertex'"),
    "ascii short row": ((HEAD + "0 0\n1 0 0\n0 1 0\n3 0 1 2\n").encode(), "corrupt PLY"),
    "ascii text": ((HEAD + "a b c\n1 0 0\n0 1 0\n3 0 1 2\n").encode(), "corrupt PLY"),
    "index out of range": ((HEAD + "0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n").encode(),
                           r"face indices out of range: face 0 has \[0, 1, 7\]"),
    "negative index": ((HEAD + "0 0 0\n1 0 0\n0 1 0\n3 0 -1 2\n").encode(), "out of range"),
    "nan vertex": ((HEAD + "0 0 0\nnan 0 0\n0 1 0\n3 0 1 2\n").encode(),
                   "1 vertices have NaN or infinite coordinates \\(first: vertex 1\\)"),
    "inf vertex": ((HEAD + "0 0 0\n1 0 0\n0 inf 0\n3 0 1 2\n").encode(), "NaN or infinite"),
    "quad": ((HEAD + "0 0 0\n1 0 0\n0 1 0\n4 0 1 2 2\n").encode(), "only triangle faces"),
    "zero faces": (HEAD.replace("face 1", "face 0").encode() + b"0 0 0\n1 0 0\n0 1 0\n",
                   "no triangles"),
    "bad count": (HEAD.replace("vertex 3", "vertex three").encode(), "header line 3"),
    "bad type": (HEAD.replace("float y", "flaot y").encode(), "unknown property type 'flaot'"),
    "bad property line": (HEAD.replace("property float z", "property float").encode(),
                          "header line 6 is malformed"),
    "no z": (HEAD.replace("property float z\n", "").encode(), "no 'z' property"),
    "bad format": (HEAD.replace("ascii", "utf8").encode(), "unsupported PLY format 'utf8'"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_corrupt_ply_names_the_file_and_the_problem(tmp_path, case):
    data, why = CASES[case]
    path = tmp_path / "model.ply"
    path.write_bytes(data)
    with pytest.raises(ValueError, match=why) as err:
        load_ply_mesh(path)
    assert str(err.value).startswith(str(path))


def test_truncated_binary_ply(tmp_path):
    data = _binary(tmp_path)
    for cut in (len(data) - 5, data.index(b"end_header") + 20):
        path = tmp_path / f"cut{cut}.ply"
        path.write_bytes(data[:cut])
        with pytest.raises(ValueError, match="truncated") as err:
            load_ply_mesh(path)
        assert str(path) in str(err.value)
    ok = tmp_path / "ok.ply"
    ok.write_bytes(data)
    v, f = load_ply_mesh(ok)
    np.testing.assert_array_equal(v, [[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]])
    np.testing.assert_array_equal(f, [[0, 1, 2], [0, 2, 3]])


def test_vertices_only_reader_accepts_a_point_cloud_but_not_nan(tmp_path):
    path = tmp_path / "cloud.ply"
    path.write_bytes(HEAD.replace("face 1", "face 0").encode() + b"0 0 0\n1 0 0\n0 1 0\n")
    np.testing.assert_array_equal(load_ply_vertices(path), [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    path.write_bytes((HEAD + "0 0 0\nnan 0 0\n0 1 0\n3 0 1 2\n").encode())
    with pytest.raises(ValueError, match="NaN"):
        load_ply_vertices(path)


def test_counts_of_another_reader_are_checked_against_the_header(tmp_path):
    path = tmp_path / "model.ply"
    path.write_bytes((HEAD + "0 0 0\n1 0 0\n").encode())
    with pytest.raises(ValueError, match="declares 3 vertex entries but the body holds 2"):
        check_ply_counts(path, 2, 0)
    check_ply_counts(path, 3, 1)
