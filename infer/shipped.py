"""The models that ship in the repository (``models/``), loaded when no run is named.

``infer.load(detector="3pt")`` and ``python -m infer bop|images|track --detector 3pt`` without
``--workdir`` (the shipped detector; the default detector is the training-free templates
detector), the default refiner (``--refiner`` unset), ``python -m train.adapt`` (unless
``--from scratch``) and the demo's zero-shot setting use them.
Each is an exported run (``python -m train.export``) with its card, ``MODEL_CARD.md``, which
says what it was trained on and what it reaches. They are verified against their
``SHA256SUMS`` before they are loaded: a missing or damaged file is named, with the command
that restores it.
"""

from __future__ import annotations

import pathlib

from threept_jax.data.run_dir import MODEL_FILES, RunDir

#: The repository's models folder (the package is installed in place: ``pip install -e .``).
MODELS_DIR = pathlib.Path(__file__).resolve().parent.parent / "models"
#: The shipped model of each kind, a folder of :data:`MODELS_DIR`; None: none ships yet.
SHIPPED: dict[str, str | None] = {"detector": "detector-cpu", "refiner": None}
#: The ``refiner`` argument of ``infer.load`` (and ``--refiner``) that picks the training-free
#: contour refiner (:mod:`infer.contour_refine`).
CONTOUR = "contour"


def restore_hint(path: pathlib.Path) -> str:
    """How to get a shipped model folder back as it was committed."""
    return (f"restore it with `git checkout -- {path.relative_to(MODELS_DIR.parent)}` in "
            f"{MODELS_DIR.parent} (the shipped weights are part of the repository)")


def shipped(kind: str) -> pathlib.Path | None:
    """The folder of the shipped ``kind`` model ("detector" or "refiner"), verified; None when
    none of that kind ships. Raises :class:`~threept_jax.data.run_dir.ModelFileError` naming a
    missing or damaged file and how to restore it."""
    from threept_jax.data.run_dir import ModelFileError

    if SHIPPED.get(kind) is None:
        return None
    path = MODELS_DIR / SHIPPED[kind]
    run = RunDir(path, kind)
    if not run.model_file.exists():
        raise ModelFileError(f"{run.model_file} not found: the shipped {kind} is missing; "
                             + restore_hint(path) + (
                                 "; a non-editable install has no models/: install with "
                                 "`pip install -e .` from a clone" if not MODELS_DIR.is_dir()
                                 else ""))
    run.verify(restore=restore_hint(path))
    return path


def default_refiner() -> pathlib.Path | str:
    """The refiner used when none is named: the shipped 3PT-R (a refiner ships only when its
    held-out check passes: it makes held-out poses better), else the training-free contour
    refiner (:data:`CONTOUR`), which needs nothing but the meshes."""
    return shipped("refiner") or CONTOUR


def describe(kind: str) -> str:
    """One line on the shipped ``kind`` model, for help texts."""
    name = SHIPPED.get(kind)
    if name is None:
        return ("the contour refiner (no 3PT-R ships yet)" if kind == "refiner"
                else f"no {kind} ships yet")
    return f"the shipped {kind}, models/{name} ({MODEL_FILES[kind][0]}, MODEL_CARD.md)"
