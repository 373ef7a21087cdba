"""Imports point one way (docs/architecture.md): each package of the project and each
subpackage of ``threept_jax`` imports only what its row of the architecture table allows.
Read from the source with ``ast`` (every import statement, function-level ones included)."""

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGES = ("threept_jax", "datagen", "train", "infer", "demo")

#: Inside ``threept_jax``: subpackage -> the subpackages it may import.
INSIDE = {
    "geometry": set(),
    "losses": {"geometry"},
    "models": {"geometry"},
    "render": {"geometry", "data"},  # data/ply.py: the PLY counts check of mesh loading
    "data": {"geometry", "models", "render"},
    "pipeline": {"geometry", "models", "render", "data"},
    "eval": {"geometry", "data"},
    "testing": {"geometry", "models", "render", "data", "pipeline", "losses", "eval"},
}
#: Project packages -> the project packages they may import (files named in EXCEPTIONS aside).
OUTSIDE = {
    "threept_jax": set(),
    "datagen": {"threept_jax"},
    "train": {"threept_jax"},
    "infer": {"threept_jax"},
    "demo": {"threept_jax", "datagen", "train", "infer"},
}
#: The orchestrators: the whole adaptation (nothing imports it but the demo and the campaign),
#: the training campaign, which makes its own data, the fit of the templates detector's
#: score (scenes made as the adaptation makes them, candidates from the detector), and the
#: candidates and per-part fit of one cell that the last two share, the training of the
#: templates detector's verifier (cells made as the adaptation makes them, candidates from the
#: detector), and the shipping of a refiner after its held-out check on the inference path.
EXCEPTIONS = {"train/adapt.py": {"threept_jax", "datagen", "infer"},
              "train/campaign.py": {"threept_jax", "datagen"},
              "train/templates_score.py": {"threept_jax", "datagen", "infer"},
              "train/cell_score.py": {"threept_jax", "infer"},
              "train/templates_verifier.py": {"threept_jax", "datagen", "infer"},
              "train/ship.py": {"threept_jax", "infer"}}


def imports(path: pathlib.Path) -> set[str]:
    """Absolute module names imported anywhere in the file."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
    return found


def _files(package: str) -> list[pathlib.Path]:
    return sorted((ROOT / package).rglob("*.py"))


@pytest.mark.parametrize("package", PACKAGES)
def test_project_packages_import_down_only(package):
    bad = []
    for f in _files(package):
        rel = f.relative_to(ROOT).as_posix()
        allowed = EXCEPTIONS.get(rel, OUTSIDE[package]) | {package}
        for m in imports(f):
            top = m.split(".")[0]
            if top in PACKAGES and top not in allowed:
                bad.append(f"{rel} imports {m}")
    assert not bad, "imports against docs/architecture.md:\n" + "\n".join(bad)


def test_threept_jax_subpackages_import_down_only():
    bad = []
    for f in _files("threept_jax"):
        parts = f.relative_to(ROOT / "threept_jax").parts
        if len(parts) == 1:
            continue  # threept_jax/__init__.py
        sub = parts[0]
        for m in imports(f):
            names = m.split(".")
            if names[0] == "threept_jax" and len(names) > 1 and names[1] != sub \
                    and names[1] not in INSIDE[sub]:
                bad.append(f"threept_jax/{'/'.join(parts)} imports {m}")
    assert not bad, "imports against docs/architecture.md:\n" + "\n".join(bad)
    assert set(INSIDE) == {p.name for p in (ROOT / "threept_jax").iterdir()
                           if (p / "__init__.py").is_file()}, "a subpackage lacks its row"


def test_the_checker_sees_a_forbidden_import(tmp_path):
    """The import reader finds function-level imports too (the rules above would pass on a
    reader that saw nothing)."""
    f = tmp_path / "m.py"
    f.write_text("import os\n\ndef f():\n    from threept_jax.pipeline.refinement import x\n")
    assert imports(f) == {"os", "threept_jax.pipeline.refinement"}
