"""Atomic file writes: the one home for "write to a temporary file, then rename".

A killed writer leaves the old file or none, never a torn one, so every resumable stage
(datagen, packing, banks, onboarding, checkpoints' side files, results) can trust what it finds
on disk. Every writer of the project goes through :func:`atomic_path`.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import pathlib
import tempfile
from collections.abc import Iterator

import numpy as np

__all__ = ["atomic_path", "atomic_write_bytes", "atomic_write_json", "atomic_savez"]


@contextlib.contextmanager
def atomic_path(path) -> Iterator[pathlib.Path]:
    """Yield a temporary path beside ``path``; on a clean exit rename it onto ``path``.

    For writers that need a file name (ArrayRecord, np.savez to disk): write to the yielded
    path inside the ``with``. On an exception the temporary file is removed and ``path`` is
    left untouched. Creates the parent folder.
    """
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        yield pathlib.Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_json(path, content, **dumps_kwargs) -> None:
    """``json.dumps(content, **dumps_kwargs)`` written atomically, with a final newline."""
    atomic_write_bytes(path, (json.dumps(content, **dumps_kwargs) + "\n").encode())


def atomic_savez(path, **arrays: np.ndarray) -> None:
    """An uncompressed ``.npz`` written atomically."""
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())
