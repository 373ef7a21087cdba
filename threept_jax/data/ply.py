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

__all__ = ["PlyHeader", "read_ply_header", "load_ply_vertices", "load_ply_mesh"]

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


def read_ply_header(data: bytes, path: str = "<bytes>") -> PlyHeader:
    """Parse the header of PLY file contents ``data``."""
    if not data.startswith(b"ply"):
        raise ValueError(f"{path} is not a PLY file (it does not start with 'ply')")
    end = data.find(b"end_header")
    if end < 0:
        raise ValueError(f"{path}: PLY header has no 'end_header' line; the file is truncated")
    newline = data.find(b"\n", end)
    body_offset = len(data) if newline < 0 else newline + 1
    fmt = None
    elements: list[PlyElement] = []
    comments: list[str] = []
    name, count, props = None, 0, []
    for raw in data[:end].decode("latin-1").splitlines():
        words = raw.split()
        if not words:
            continue
        key = words[0]
        if key == "format":
            fmt = words[1]
        elif key in ("comment", "obj_info"):
            comments.append(raw.strip()[len(key) :].strip())
        elif key == "element":
            if name is not None:
                elements.append(PlyElement(name, count, tuple(props)))
            name, count, props = words[1], int(words[2]), []
        elif key == "property":
            if name is None:
                raise ValueError(f"{path}: PLY property outside an element: {raw!r}")
            if words[1] == "list":
                props.append((words[4], words[3], words[2]))
            else:
                props.append((words[2], words[1], None))
    if name is not None:
        elements.append(PlyElement(name, count, tuple(props)))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ValueError(f"{path}: unsupported PLY format {fmt!r}")
    return PlyHeader(fmt, tuple(elements), body_offset, tuple(comments))


def _scalar_dtype(el: PlyElement, endian: str, path: str) -> np.dtype:
    fields = []
    for prop, typ, list_type in el.properties:
        if list_type is not None:
            raise ValueError(
                f"{path}: element {el.name!r} has a list property {prop!r}; only the face "
                "element may carry lists in a binary PLY read by this reader"
            )
        if typ not in _PLY_TYPES:
            raise ValueError(f"{path}: unknown PLY property type {typ!r}")
        fields.append((prop, endian + _PLY_TYPES[typ]))
    return np.dtype(fields)


def _read_body(path: pathlib.Path, want_faces: bool):
    data = path.read_bytes()
    header = read_ply_header(data, str(path))
    vertex = header.element("vertex")
    if vertex is None:
        raise ValueError(f"{path}: PLY file has no vertex element")
    names = [p[0] for p in vertex.properties]
    for axis in ("x", "y", "z"):
        if axis not in names:
            raise ValueError(f"{path}: PLY vertex element has no {axis!r} property")
    faces = None
    if header.format == "ascii":
        lines = data[header.body_offset :].decode("latin-1").splitlines()
        offset = 0
        verts = None
        for el in header.elements:
            block = lines[offset : offset + el.count]
            if len(block) < el.count:
                raise ValueError(f"{path}: PLY body ends inside element {el.name!r}")
            if el.name == "vertex":
                cols = [names.index(a) for a in ("x", "y", "z")]
                verts = np.loadtxt(block, dtype=np.float64, usecols=cols, ndmin=2)
                if verts.shape != (el.count, 3):
                    raise ValueError(f"{path}: could not parse {el.count} vertices")
            elif el.name == "face" and want_faces:
                rows = [row.split() for row in block]
                if any(int(r[0]) != 3 for r in rows):
                    raise ValueError(f"{path}: only triangle faces are supported")
                faces = np.array([r[1:4] for r in rows], dtype=np.int64).reshape(-1, 3)
            offset += el.count
        return verts, faces
    endian = "<" if header.format == "binary_little_endian" else ">"
    pos = header.body_offset
    verts = None
    for el in header.elements:
        if el.name == "face" and any(p[2] is not None for p in el.properties):
            if not want_faces:
                break
            if len(el.properties) != 1:
                raise ValueError(f"{path}: binary faces with extra properties are not supported")
            _, idx_type, cnt_type = el.properties[0]
            rec = np.dtype(
                [("n", endian + _PLY_TYPES[cnt_type]), ("v", endian + _PLY_TYPES[idx_type], (3,))]
            )
            arr = np.frombuffer(data, dtype=rec, count=el.count, offset=pos)
            if np.any(arr["n"] != 3):
                raise ValueError(f"{path}: only triangle faces are supported")
            faces = arr["v"].astype(np.int64)
            pos += rec.itemsize * el.count
            continue
        dt = _scalar_dtype(el, endian, str(path))
        arr = np.frombuffer(data, dtype=dt, count=el.count, offset=pos)
        if el.name == "vertex":
            verts = np.stack([arr["x"], arr["y"], arr["z"]], axis=1).astype(np.float64)
        pos += dt.itemsize * el.count
    return verts, faces


def load_ply_vertices(path: str | pathlib.Path) -> np.ndarray:
    """All vertices of a PLY file in file order: [N, 3] float64 (model units, mm in BOP)."""
    verts, _ = _read_body(pathlib.Path(path), want_faces=False)
    return verts


def load_ply_mesh(path: str | pathlib.Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices [N, 3] float64 and triangle faces [F, 3] int64 of a PLY file."""
    verts, faces = _read_body(pathlib.Path(path), want_faces=True)
    if faces is None:
        faces = np.zeros((0, 3), np.int64)
    return verts, faces
