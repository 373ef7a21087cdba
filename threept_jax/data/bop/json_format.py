"""BOP JSON: formatted like `bop_toolkit_lib.inout.save_json`, read with clear errors."""

from __future__ import annotations

import io
import json
import pathlib
from collections.abc import Mapping

from threept_jax.data.files import atomic_write_bytes


def _json_dumps_bop(content) -> str:
    """Format like `bop_toolkit_lib.inout.save_json`: one top-level entry per line."""
    buf = io.StringIO()
    if isinstance(content, Mapping):
        items = sorted(content.items(), key=lambda kv: kv[0])
        buf.write("{\n")
        for i, (k, v) in enumerate(items):
            buf.write(f'  "{k}": {json.dumps(v, sort_keys=True)}')
            buf.write(",\n" if i != len(items) - 1 else "\n")
        buf.write("}")
    elif isinstance(content, list):
        buf.write("[\n")
        for i, v in enumerate(content):
            buf.write(f"  {json.dumps(v, sort_keys=True)}")
            buf.write(",\n" if i != len(content) - 1 else "\n")
        buf.write("]")
    else:
        buf.write(json.dumps(content, sort_keys=True))
    return buf.getvalue()


def write_json_atomic(path, content) -> None:
    """Write ``content`` as BOP-formatted JSON to ``path`` via a temporary file and rename."""
    atomic_write_bytes(pathlib.Path(path), _json_dumps_bop(content).encode())


def _load_json(path: pathlib.Path):
    if not path.is_file():
        raise FileNotFoundError(f"missing BOP file {path}")
    try:
        with open(path) as f:
            return json.load(f)
    except json.JSONDecodeError as e:
        raise ValueError(f"{path} is not valid JSON ({e}); the file is probably truncated") from e


def _int_keys(d: Mapping, path) -> dict:
    out = {}
    for k, v in d.items():
        try:
            out[int(k)] = v
        except ValueError:
            raise ValueError(f"{path}: key {k!r} is not an integer image id") from None
    return out
