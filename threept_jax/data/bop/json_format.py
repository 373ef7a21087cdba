"""BOP JSON: formatted like `bop_toolkit_lib.inout.save_json`, read with clear errors."""

from __future__ import annotations

import contextlib
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


def _short(v, n: int = 60) -> str:
    """repr of ``v`` cut to ``n`` characters (a garbage file can hold huge values)."""
    r = repr(v)
    return r if len(r) <= n else r[: n - 3] + "..."


def _read_text(path: pathlib.Path, what: str) -> str:
    """The UTF-8 text of a BOP file (a leading BOM is dropped): FileNotFoundError when it is
    missing, ValueError naming the file and the first undecodable line when it is not UTF-8."""
    if not path.is_file():
        raise FileNotFoundError(f"{what} {path} does not exist")
    data = path.read_bytes()
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = data[: e.start].count(b"\n") + 1
        raise ValueError(
            f"{path}:{line}: not UTF-8 text (byte {e.start}: {e.reason}): {path.name} is not "
            f"UTF-8, so it is no {what}"
        ) from None


def _load_json(path: pathlib.Path, what: str = "BOP JSON file"):
    """Parse a JSON file; any unreadable content is a ValueError naming the file."""
    text = _read_text(path, what)
    try:
        return json.loads(text)
    except RecursionError:
        raise ValueError(f"{path}: JSON nested too deeply to be a {what}") from None
    except ValueError as e:  # json.JSONDecodeError, or an integer literal of 5000 digits
        raise ValueError(
            f"{path} is not valid JSON ({_short(str(e), 200)}); is the file truncated?"
        ) from None


def _int_keys(d, path) -> dict:
    """``{"12": v}`` -> ``{12: v}``: BOP keys per-image files by the image id as a string."""
    if not isinstance(d, Mapping):
        raise ValueError(f"{path}: expected a JSON object keyed by id, got {type(d).__name__}")
    out = {}
    for k, v in d.items():
        try:
            out[int(k)] = v
        except ValueError:
            raise ValueError(f"{path}: key {k!r} is not an integer id") from None
    return out


def _json_int(v) -> int:
    """An id or count from JSON: an integer (or an integral float, as NumPy writers produce);
    refuses booleans, fractions, NaN and strings instead of truncating them."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise TypeError(f"expected an integer, got {v!r}")
    if isinstance(v, float) and not v.is_integer():
        raise ValueError(f"expected an integer, got {v!r}")
    return int(v)


@contextlib.contextmanager
def entry_errors(where: str, expected: str):
    """Report a structurally wrong JSON entry (a missing key, a list where a number belongs, a
    NaN where an integer belongs, a wrong length) as a ValueError naming ``where`` (the file and
    the entry) and the expected form, instead of the TypeError or KeyError raised deep inside
    the parsing. ValueErrors that already name ``where`` pass through unchanged."""
    try:
        yield
    except ValueError as e:
        if where in str(e):
            raise
        raise ValueError(f"{where}: {e}; expected {expected}") from None
    except (KeyError, TypeError, IndexError, AttributeError, OverflowError) as e:
        raise ValueError(
            f"{where}: malformed entry ({type(e).__name__}: {e}); expected {expected}") from None
