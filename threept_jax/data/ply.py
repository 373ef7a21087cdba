"""A small PLY reader for BOP object models: vertices (and triangle faces) as float64.

BOP evaluates pose errors on *every* vertex of a model, exactly as stored in the PLY file
(`bop_toolkit_lib/inout.py::load_ply` keeps all vertices, in file order, as float64). General
mesh loaders may merge, split or drop vertices (texture seams, unreferenced vertices), which
would change ADD and could change MSSD/MSPD, so the evaluator reads vertices with this reader.
ASCII and binary (little/big endian) PLY are supported; only the ``x, y, z`` vertex properties
and ``vertex_indices`` triangle faces are returned.
"""

from __future__ import annotations

import pathlib
from dataclasses import dataclass

import numpy as np

from threept_jax.geometry.validate import validate_mesh_arrays, validate_vertices

__all__ = [
    "PlyHeader",
    "read_ply_header",
    "check_ply_counts",
    "load_ply_vertices",
    "load_ply_mesh",
]

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


@dataclass(frozen=True)
class PlyElement:
    """One ``element`` of a PLY header: name, count and ``(name, type, list_count_type)`` props."""

    name: str
    count: int
    properties: tuple[tuple[str, str, str | None], ...]


@dataclass(frozen=True)
class PlyHeader:
    """Parsed PLY header: format, elements in file order, byte offset of the body, comments."""

    format: str
    elements: tuple[PlyElement, ...]
    body_offset: int
    comments: tuple[str, ...]

    def element(self, name: str) -> PlyElement | None:
        for el in self.elements:
            if el.name == name:
                return el
        return None


class _PlyError(ValueError):
    """A problem this reader found and described (its message names the file)."""


def read_ply_header(data: bytes, path: str = "<bytes>") -> PlyHeader:
    """Parse the header of PLY file contents ``data``; ValueError naming ``path`` if corrupt."""
    if not data.startswith(b"ply"):
        raise _PlyError(f"{path} is not a PLY file (it does not start with 'ply')")
    end = data.find(b"end_header")
    if end < 0:
        raise _PlyError(f"{path}: PLY header has no 'end_header' line; the file is truncated")
    newline = data.find(b"\n", end)
    body_offset = len(data) if newline < 0 else newline + 1
    fmt = None
    elements: list[PlyElement] = []
    comments: list[str] = []
    name, count, props = None, 0, []
    for line_no, raw in enumerate(data[:end].decode("latin-1").splitlines(), start=1):
        words = raw.split()
        if not words:
            continue
        key = words[0]
        bad = _PlyError(f"{path}: PLY header line {line_no} is malformed: {raw.strip()!r}")
        if key == "format":
            if len(words) < 2:
                raise bad
            fmt = words[1]
        elif key in ("comment", "obj_info"):
            comments.append(raw.strip()[len(key) :].strip())
        elif key == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise bad
            if name is not None:
                elements.append(PlyElement(name, count, tuple(props)))
            name, count, props = words[1], int(words[2]), []
        elif key == "property":
            if name is None:
                raise _PlyError(f"{path}: PLY property outside an element: {raw!r}")
            if len(words) == 5 and words[1] == "list":
                types = (words[2], words[3])
                props.append((words[4], words[3], words[2]))
            elif len(words) == 3:
                types = (words[1],)
                props.append((words[2], words[1], None))
            else:
                raise bad
            unknown = [t for t in types if t not in _PLY_TYPES]
            if unknown:
                raise _PlyError(
                    f"{path}: PLY header line {line_no}: unknown property type {unknown[0]!r} "
                    f"(known: {', '.join(sorted(_PLY_TYPES))})"
                )
    if name is not None:
        elements.append(PlyElement(name, count, tuple(props)))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise _PlyError(f"{path}: unsupported PLY format {fmt!r}")
    return PlyHeader(fmt, tuple(elements), body_offset, tuple(comments))


def check_ply_counts(path: str | pathlib.Path, num_vertices: int, num_faces: int) -> None:
    """Raise ValueError naming ``path`` unless another reader's counts match its PLY header.

    General readers (trimesh) return what they could parse of a truncated file without a word;
    comparing with the element counts the header declares catches that.
    """
    path = pathlib.Path(path)
    with open(path, "rb") as fh:
        head = fh.read(1 << 20)
    if b"end_header" not in head:
        head = path.read_bytes()
    header = read_ply_header(head, str(path))
    want = {el.name: el.count for el in header.elements}
    got = {"vertex": num_vertices, "face": num_faces}
    for name, n in got.items():
        if name in want and n < want[name]:
            raise _PlyError(
                f"{path}: the header declares {want[name]} {name} entries but the body holds "
                f"{n}; the file is truncated"
            )


def _scalar_dtype(el: PlyElement, endian: str, path: str) -> np.dtype:
    fields = []
    for prop, typ, list_type in el.properties:
        if list_type is not None:
            raise _PlyError(
                f"{path}: element {el.name!r} has a list property {prop!r}; only the face "
                "element may carry lists in a binary PLY read by this reader"
            )
        fields.append((prop, endian + _PLY_TYPES[typ]))
    return np.dtype(fields)


def _take(data: bytes, dtype: np.dtype, el: PlyElement, pos: int, path: str) -> np.ndarray:
    """el.count records of ``dtype`` at byte ``pos`` of ``data``, or a truncation error."""
    need = dtype.itemsize * el.count
    if pos + need > len(data):
        raise _PlyError(
            f"{path}: PLY body ends inside element {el.name!r} ({el.count} entries need "
            f"{need} bytes, {max(len(data) - pos, 0)} left); the file is truncated"
        )
    return np.frombuffer(data, dtype=dtype, count=el.count, offset=pos)


def _parse(data: bytes, path: str, want_faces: bool):
    header = read_ply_header(data, path)
    vertex = header.element("vertex")
    if vertex is None:
        raise _PlyError(f"{path}: PLY file has no vertex element")
    names = [p[0] for p in vertex.properties]
    for axis in ("x", "y", "z"):
        if axis not in names:
            raise _PlyError(f"{path}: PLY vertex element has no {axis!r} property")
    faces = None
    verts = None
    if header.format == "ascii":
        lines = data[header.body_offset :].decode("latin-1").splitlines()
        offset = 0
        for el in header.elements:
            block = lines[offset : offset + el.count]
            if len(block) < el.count:
                raise _PlyError(f"{path}: PLY body ends inside element {el.name!r}")
            if el.name == "vertex":
                cols = [names.index(a) for a in ("x", "y", "z")]
                verts = np.loadtxt(block, dtype=np.float64, usecols=cols, ndmin=2)
                if verts.shape != (el.count, 3):
                    raise _PlyError(f"{path}: could not parse {el.count} vertices")
            elif el.name == "face" and want_faces:
                rows = [row.split() for row in block]
                if any(len(r) < 4 or r[0] != "3" for r in rows):
                    raise _PlyError(f"{path}: only triangle faces are supported")
                faces = np.array([r[1:4] for r in rows], dtype=np.int64).reshape(-1, 3)
            offset += el.count
        return verts, faces
    endian = "<" if header.format == "binary_little_endian" else ">"
    pos = header.body_offset
    for el in header.elements:
        if el.name == "face" and any(p[2] is not None for p in el.properties):
            if not want_faces:
                break
            if len(el.properties) != 1:
                raise _PlyError(f"{path}: binary faces with extra properties are not supported")
            _, idx_type, cnt_type = el.properties[0]
            rec = np.dtype(
                [("n", endian + _PLY_TYPES[cnt_type]), ("v", endian + _PLY_TYPES[idx_type], (3,))]
            )
            arr = _take(data, rec, el, pos, path)
            if np.any(arr["n"] != 3):
                raise _PlyError(f"{path}: only triangle faces are supported")
            faces = arr["v"].astype(np.int64)
            pos += rec.itemsize * el.count
            continue
        dt = _scalar_dtype(el, endian, path)
        arr = _take(data, dt, el, pos, path)
        if el.name == "vertex":
            verts = np.stack([arr["x"], arr["y"], arr["z"]], axis=1).astype(np.float64)
        pos += dt.itemsize * el.count
    return verts, faces


def _read_body(path: pathlib.Path, want_faces: bool):
    data = path.read_bytes()
    try:
        verts, faces = _parse(data, str(path), want_faces)
    except _PlyError:
        raise
    except (ValueError, IndexError, KeyError, TypeError, OverflowError) as e:
        # numpy's own words ("could not convert string to float", ...) under the file's name.
        raise ValueError(f"{path}: corrupt PLY file ({type(e).__name__}: {e})") from None
    if want_faces:
        validate_mesh_arrays(verts, faces, path)
    else:
        validate_vertices(verts, path)
    return verts, faces


def load_ply_vertices(path: str | pathlib.Path) -> np.ndarray:
    """All vertices of a PLY file in file order: [N, 3] float64 (model units, mm in BOP).

    Raises ValueError naming the file when it is not a readable PLY (truncated, corrupt,
    unsupported) or has no vertices or non-finite ones.
    """
    verts, _ = _read_body(pathlib.Path(path), want_faces=False)
    return verts


def load_ply_mesh(path: str | pathlib.Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices [N, 3] float64 and triangle faces [F, 3] int64 of a PLY file.

    Raises ValueError naming the file for everything :func:`load_ply_vertices` refuses, and
    for a file without faces or with face indices outside the vertex range.
    """
    return _read_body(pathlib.Path(path), want_faces=True)
