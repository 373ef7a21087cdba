"""The models that ship in the repository (``models/``), loaded when no run is named.

``infer.load(detector="3pt")`` and ``python -m infer bop|images|track --detector 3pt`` without
``--workdir`` (the shipped detector; the default detector is the training-free templates
detector), the default refiner (``--refiner`` unset), ``python -m train.adapt`` (unless
``--from scratch``) and the demo's zero-shot setting use them.
Each is an exported run (``python -m train.export``) with its card, ``MODEL_CARD.md``, which
says what it was trained on and what it reaches. ``models/shipped.json`` names the shipped
model of each kind (:data:`SHIPPED_FILE`); ``python -m train.ship`` changes it only for a
refiner that refines held-out scenes better than the default. They are verified against their
``SHA256SUMS`` before they are loaded: a missing or damaged file is named, with the command
that restores it.
"""

from __future__ import annotations

import json
import os
import pathlib

from threept_jax.data.run_dir import MODEL_FILES, ModelFileError, RunDir

#: The repository's models folder (the package is installed in place: ``pip install -e .``).
MODELS_DIR = pathlib.Path(__file__).resolve().parent.parent / "models"
#: The file of :data:`MODELS_DIR` that names the shipped model of each kind, ``{"detector":
#: FOLDER | null, "refiner": FOLDER | null}`` (a folder of :data:`MODELS_DIR`; null: none ships).
SHIPPED_FILE = "shipped.json"
#: The ``refiner`` argument of ``infer.load`` (and ``--refiner``) that picks the training-free
#: contour refiner (:mod:`infer.contour_refine`).
CONTOUR = "contour"


def restore_hint(path: pathlib.Path) -> str:
    """How to get a shipped model folder back as it was committed."""
    return (f"restore it with `git checkout -- {path.relative_to(MODELS_DIR.parent)}` in "
            f"{MODELS_DIR.parent} (the shipped weights are part of the repository)")


_NOT_EDITABLE = "; a non-editable install has no models/: install with `pip install -e .` from a clone"


def shipped_names() -> dict[str, str | None]:
    """{kind: the folder of :data:`MODELS_DIR` that ships, or None} from :data:`SHIPPED_FILE`.
    Raises :class:`~threept_jax.data.run_dir.ModelFileError` when it is missing or malformed,
    saying how to restore it."""
    path = MODELS_DIR / SHIPPED_FILE
    if not path.is_file():
        raise ModelFileError(f"{path} not found: it names the shipped models; "
                             + restore_hint(path) + ("" if MODELS_DIR.is_dir() else _NOT_EDITABLE))
    try:
        names = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ModelFileError(f"{path} is not JSON ({e}); {restore_hint(path)}") from None
    if (not isinstance(names, dict) or set(names) != set(MODEL_FILES)
            or not all(v is None or (isinstance(v, str) and v) for v in names.values())):
        raise ModelFileError(f"{path} must map {sorted(MODEL_FILES)} each to a folder of "
                             f"models/ or null, got {names!r}; {restore_hint(path)}")
    return names


def set_shipped(kind: str, name: str) -> None:
    """Name ``MODELS_DIR/name`` the shipped ``kind`` model in :data:`SHIPPED_FILE` (written
    whole, then renamed onto the old file). Only ``python -m train.ship`` calls it, after its
    held-out check."""
    names = shipped_names()
    if kind not in names or not (MODELS_DIR / name / MODEL_FILES[kind][0]).is_file():
        raise ValueError(f"{MODELS_DIR / name} is not a {kind} model folder")
    names[kind] = name
    path = MODELS_DIR / SHIPPED_FILE
    tmp = path.with_name(f".{path.name}.{os.getpid()}")
    tmp.write_text(json.dumps(names, indent=1) + "\n")
    tmp.replace(path)


def shipped(kind: str) -> pathlib.Path | None:
    """The folder of the shipped ``kind`` model ("detector" or "refiner"), verified; None when
    none of that kind ships. Raises :class:`~threept_jax.data.run_dir.ModelFileError` naming a
    missing or damaged file and how to restore it."""
    name = shipped_names()[kind]
    if name is None:
        return None
    path = MODELS_DIR / name
    run = RunDir(path, kind)
    if not run.model_file.exists():
        raise ModelFileError(f"{run.model_file} not found: the shipped {kind} is missing; "
                             + restore_hint(path) + ("" if MODELS_DIR.is_dir() else _NOT_EDITABLE))
    run.verify(restore=restore_hint(path))
    return path


def default_refiner() -> pathlib.Path | str:
    """The refiner used when none is named: the shipped 3PT-R (a refiner ships only when its
    held-out check passes: it refines held-out scenes better, ``python -m train.ship``), else
    the training-free contour refiner (:data:`CONTOUR`), which needs nothing but the meshes.
    A non-editable install, which has no models/, refines with the contour refiner."""
    if not MODELS_DIR.is_dir():
        return CONTOUR
    return shipped("refiner") or CONTOUR


def describe(kind: str) -> str:
    """One line on the shipped ``kind`` model, for help texts."""
    try:
        name = shipped_names()[kind]
    except ModelFileError:
        return f"the shipped {kind} (models/{SHIPPED_FILE} is missing or damaged)"
    if name is None:
        return ("the contour refiner (no 3PT-R ships yet)" if kind == "refiner"
                else f"no {kind} ships yet")
    return f"the shipped {kind}, models/{name} ({MODEL_FILES[kind][0]}, MODEL_CARD.md)"
