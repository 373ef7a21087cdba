"""Command line: evaluate a BOP 6D results CSV or 2D results JSON against a BOP dataset.

    python -m threept_jax.eval --dataset-dir DIR --split test --results FILE --out scores.json \\
        [--targets FILE] [--models-subdir models_eval] [--sensor NAME] [--image-width PX]
        [--max-estimates-per-image N] [--rotation-atol TOL]

Writes a JSON with ``ap, ap_mssd, ap_mspd, ap_mm, ar_mssd, ar_mspd, per_object, num_estimates,
num_gt`` (6D) or ``bbox`` / ``segm`` each ``{ap, ap50, ap75}`` (2D), and prints a table.
"""

from __future__ import annotations

import argparse
import pathlib
import sys

from threept_jax.data.bop import write_json_atomic
from threept_jax.eval.bop6d import PoseScores
from threept_jax.eval.bop_eval import (
    check_positive_float,
    check_positive_int,
    evaluate_results_file,
)


def _fmt(v) -> str:
    return "   -  " if v is None else f"{100.0 * v:6.2f}"


def format_table(scores) -> str:
    """A readable text table of 6D (PoseScores) or 2D (dict) scores, values in percent."""
    lines = []
    if isinstance(scores, PoseScores):
        keys = ["ap", "ap_mssd", "ap_mspd", "ap_mm", "ar_mssd", "ar_mspd"]
        lines.append("obj_id  " + "  ".join(f"{k:>7s}" for k in keys))
        for o, d in sorted(scores.per_object.items()):
            lines.append(f"{o:6d}  " + "  ".join(f"{_fmt(d.get(k)):>7s}" for k in keys))
        lines.append("-" * len(lines[0]))
        lines.append("   all  " + "  ".join(f"{_fmt(getattr(scores, k)):>7s}" for k in keys))
        lines.append(f"estimates evaluated: {scores.num_estimates}, GT counted: {scores.num_gt}")
    else:
        lines.append("type        AP    AP50    AP75")
        for t, d in scores.items():
            lines.append(f"{t:5s}  {_fmt(d['ap'])}  {_fmt(d['ap50'])}  {_fmt(d['ap75'])}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m threept_jax.eval", description=__doc__.split("\n")[0]
    )
    ap.add_argument("--dataset-dir", required=True, help="BOP dataset folder (e.g. .../tless)")
    ap.add_argument("--split", default="test", help="split folder name (default: test)")
    ap.add_argument("--results", required=True, help="6D results .csv or 2D results .json")
    ap.add_argument("--out", required=True, help="where to write the scores JSON")
    ap.add_argument(
        "--targets",
        default=None,
        help="targets JSON (default: test_targets_bop24.json, else _bop19.json)",
    )
    ap.add_argument(
        "--models-subdir",
        default=None,
        help="models folder (default: models_eval when present, else models)",
    )
    ap.add_argument(
        "--sensor", default=None, help="sensor of multi-sensor datasets (e.g. photoneo)"
    )
    ap.add_argument(
        "--image-width",
        type=int,
        default=None,
        help="image width in px for MSPD normalisation (default: camera.json/image)",
    )
    ap.add_argument(
        "--max-estimates-per-image",
        type=int,
        default=None,
        help="top estimates kept per image (default 100, 200 for xyzibd)",
    )
    ap.add_argument(
        "--rotation-atol",
        type=float,
        default=1e-3,
        help="largest |R R^T - I| entry accepted for a rotation in a 6D results file "
        "(default 1e-3); the dataset's GT rotations are accepted as the toolkit does",
    )
    args = ap.parse_args(argv)
    kwargs = dict(
        split=args.split,
        targets_path=args.targets,
        models_subdir=args.models_subdir,
        sensor=args.sensor,
    )
    try:
        if args.image_width is not None:
            check_positive_int(args.image_width, "--image-width")
        if args.max_estimates_per_image is not None:
            check_positive_int(args.max_estimates_per_image, "--max-estimates-per-image")
        check_positive_float(args.rotation_atol, "--rotation-atol")
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if pathlib.Path(args.results).suffix.lower() == ".csv":
        kwargs.update(
            image_width=args.image_width,
            max_estimates_per_image=args.max_estimates_per_image,
            rotation_atol=args.rotation_atol,
        )
    try:
        scores = evaluate_results_file(args.dataset_dir, args.results, **kwargs)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    out = scores.to_json() if isinstance(scores, PoseScores) else scores
    write_json_atomic(args.out, out)
    print(format_table(scores))
    print(f"scores written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
