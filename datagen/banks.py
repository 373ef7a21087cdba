"""Render banks for the detector: ``python -m datagen.banks`` (also run by ``datagen.pack``).

For every object of a records folder's ``objects.json`` (``threept_jax.data.banks``), render
the 12 prior views (``grids.prior_view_rotations()``) and T templates
(``grids.super_fibonacci_rotations(T)``) with ``threept_jax.pipeline.onboarding
.render_bank`` (the bank camera of ``threept_jax.data.banks``; JAX rasterizer, shaded
``rgb``, textures and vertex colours used) and store them with their rotations, the model's
diameter, bounding sphere and symmetries as ``banks/obj_XXXXXX.npz``::

    python -m datagen.banks --records OUT [--size 96] [--num-templates 5140] [--force]

``--size`` must be the detector's ``render_size``: training uses the renders as stored and
inference onboarding renders at that size with the same function
(``threept_jax.pipeline.onboarding``, supersampled 3x and box-averaged), so both see the same
images. Meshes come from the table's ``mesh`` field (written by ``datagen.pack``). Banks whose size and
template count already match are kept unless ``--force``. Meshes above ``--max-faces`` are
decimated for the rasterizer (the camera stays the full model's); renders go in chunks, so
memory is bounded for any T.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
from collections.abc import Sequence

from threept_jax.data import banks as B
from threept_jax.geometry.symmetry import Symmetries
from threept_jax.pipeline.onboarding import render_bank


class TableError(ValueError):
    """The object table cannot be used for rendering banks (the message names the fix)."""


def bank_is_current(path: pathlib.Path, size: int, num_templates: int) -> bool:
    """Whether ``path`` is a readable bank of ``size`` renders and ``num_templates`` templates."""
    if not path.is_file():
        return False
    try:
        f = B.BankFile(path)
    except (ValueError, OSError):
        return False
    return f.image_hw == (size, size) and f.num_templates == num_templates


def build_banks(
    records_dir: pathlib.Path,
    obj_ids: Sequence[int] | None = None,
    size: int = B.BANK_SIZE,
    num_templates: int = B.BANK_TEMPLATES,
    *,
    force: bool = False,
    max_faces: int | None = 20000,
    image_format: str = "png",
    backend: str = "jax",
    quiet: bool = False,
) -> list[int]:
    """Render the missing or outdated banks of ``records_dir/objects.json``; returns the ids.

    Each bank goes to the row's ``bank`` path (atomically). A table row without a ``mesh``
    field cannot be rendered and raises with the fix.
    """
    from tqdm import tqdm

    records_dir = pathlib.Path(records_dir)
    table_path = records_dir / "objects.json"
    if not table_path.is_file():
        raise TableError(f"{table_path} is missing; write it with `python -m datagen.pack`")
    raw = json.loads(table_path.read_text())
    todo = []
    for key in sorted(raw, key=int):
        oid = int(key)
        if obj_ids is not None and oid not in obj_ids:
            continue
        row = raw[key]
        if "mesh" not in row:
            raise TableError(
                f"{table_path} object {oid} has no 'mesh' path; re-pack with "
                "`python -m datagen.pack` (it copies the models and records their paths)"
            )
        bank = records_dir / row["bank"]
        if force or not bank_is_current(bank, size, num_templates):
            todo.append((oid, row, bank))
    views = len(todo) * (12 + num_templates)
    with tqdm(total=views, unit="view", desc="render banks", disable=quiet or not todo,
              dynamic_ncols=True) as bar:
        for oid, row, bank in todo:
            symmetries = Symmetries.from_json(row, f"{table_path} object {oid}")
            rb = render_bank(records_dir / row["mesh"], oid, float(row["diameter"]), symmetries,
                             size, num_templates, max_faces=max_faces, backend=backend,
                             on_views=bar.update)
            B.save_bank(bank, rb, image_format=image_format)
    return [t[0] for t in todo]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m datagen.banks",
        description="Render the detector's prior views and template banks of a records folder.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--records", required=True, help="folder holding objects.json")
    p.add_argument("--size", type=int, default=B.BANK_SIZE,
                   help="render side, pixels: the detector's render_size (tiny 32, small 112, "
                        "paper 224); renders are supersampled 3x and never resized")
    p.add_argument("--num-templates", type=int, default=B.BANK_TEMPLATES)
    p.add_argument("--obj-ids", type=int, nargs="*", default=None)
    p.add_argument("--max-faces", type=int, default=20000,
                   help="decimate larger meshes for the rasterizer")
    p.add_argument("--image-format", choices=("png", "jpg"), default="png")
    p.add_argument("--backend", choices=("jax", "mitsuba"), default="jax",
                   help="renderer (both give the same shaded images)")
    p.add_argument("--force", action="store_true", help="re-render existing banks")
    p.add_argument("--quiet", action="store_true")
    return p


def main(argv: Sequence[str] | None = None) -> list[int]:
    parser = build_parser()
    args = parser.parse_args(argv)
    for flag, value, least in (("--size", args.size, 8), ("--num-templates", args.num_templates, 1),
                               ("--max-faces", args.max_faces, 4)):
        if value < least:
            parser.error(f"{flag} must be >= {least}, got {value}")  # exits 2
    try:
        done = build_banks(pathlib.Path(args.records), args.obj_ids, args.size,
                           args.num_templates, force=args.force, max_faces=args.max_faces,
                           image_format=args.image_format, backend=args.backend,
                           quiet=args.quiet)
    except TableError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    if not args.quiet:
        print(f"rendered {len(done)} banks")
    return done


if __name__ == "__main__":
    main()
