"""Ship a trained 3PT-R only when it refines held-out scenes better than today's default:
``python -m train.ship --run models/refiner-gpu-run --name gpu --dataset-dir HELD_OUT``.

The check is the real inference path, twice, on the ``val_pbr`` images of a held-out BOP
dataset (``python -m infer bop --evaluate``: the default detector, every part of the dataset
queried, every detection kept, so both runs refine the same detections): once refined by the
run's best checkpoint, once by the refiner used today (``infer.shipped.default_refiner``: the
shipped 3PT-R, else the training-free contour refiner). The run ships only when its BOP 6D AP
is higher (by any margin: the dataset is the user's choice, and a larger one makes the margin
mean more):

* it is exported (``train.export``) to ``models/refiner-NAME``, with a card written from the
  figures (``MODEL_CARD.md``: what the model is, how it was trained, the check's figures and
  command);
* ``models/shipped.json`` names it, so ``infer.load()``, ``python -m infer bop|images|track``
  without ``--refiner`` and the demo load it from then on (commit both to keep them).

Otherwise nothing under ``models/`` changes and the figures say why. Either way they are
written to ``OUT/ship_check.json`` (``--out``, default ``runs/ship/NAME``, with the check's
inference outputs). With ``--records`` (refiner records of held-out parts) the
card also gives the run's matching and pose figures on them (``train.eval_refiner``), a
diagnostic beside the inference path's figures.

Use a held-out dataset of parts the run never trained on (a zero-shot cell: ``python -m
train.adapt``'s ``generate`` with another ``--seed``, or the demo's ``runs/demo/zero_shot/data/
test``): the default refiner needs no training, so it works on any part, and its replacement
must too.
"""

from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import re
import shlex
import shutil
import sys
from collections.abc import Sequence

#: A model name: ``models/refiner-NAME``.
NAME = re.compile(r"[a-z0-9][a-z0-9_.-]*")
#: The figure that decides (``train.adapt.figures``: BOP 6D AP after refinement).
DECIDES = "pose_ap"


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m train.ship", description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--run", type=pathlib.Path, required=True,
                   help="a 3PT-R training run (its best checkpoint is checked)")
    p.add_argument("--name", required=True, help="ships as models/refiner-NAME")
    p.add_argument("--dataset-dir", type=pathlib.Path, required=True,
                   help="a held-out BOP dataset whose val_pbr images the check refines")
    p.add_argument("--records", type=pathlib.Path, default=None,
                   help="refiner records of held-out parts: the card's matching diagnostic")
    p.add_argument("--max-detections", type=int, default=12, help="per image, for the AP")
    p.add_argument("--out", type=pathlib.Path, default=None,
                   help="the check's inference outputs and ship_check.json (default: "
                        "runs/ship/NAME)")
    args = p.parse_args(argv)
    if not (args.run / "refiner.json").is_file():
        p.error(f"--run {args.run} is not a 3PT-R training run (no refiner.json): pass the "
                "--workdir of python train/launch.py --config train/configs/refiner.py:...")
    if not NAME.fullmatch(args.name):
        p.error(f"--name {args.name!r}: use lower-case letters, digits, '.', '_' and '-'")
    if not (args.dataset_dir / "val_pbr").is_dir():
        p.error(f"--dataset-dir {args.dataset_dir} has no val_pbr split: pass a BOP dataset of "
                "held-out scenes (python -m datagen.generate --split val)")
    if args.records is not None and not (args.records / "objects.json").is_file():
        p.error(f"--records {args.records} is not a records folder (no objects.json)")
    if args.max_detections < 1:
        p.error("--max-detections must be >= 1")
    from infer import shipped

    folder = shipped.MODELS_DIR / f"refiner-{args.name}"
    if folder.exists() and shipped.shipped_names()["refiner"] != folder.name:
        p.error(f"--name {args.name}: {folder} exists and is not the shipped refiner; choose "
                "another name")
    args.out = args.out or pathlib.Path("runs") / "ship" / args.name
    return args


def check(run: pathlib.Path, dataset: pathlib.Path, out: pathlib.Path,
          max_detections: int) -> dict:
    """The held-out figures of ``run`` and of today's default refiner on ``dataset`` (module
    docstring): ``{"candidate": figures, "default": figures, "default_refiner": str}``, the
    figures of :func:`train.adapt.figures`."""
    from infer.shipped import default_refiner
    from train import adapt

    current = default_refiner()
    figures = {}
    for key, refiner in (("candidate", run), ("default", current)):
        summary = adapt.infer_bop(None, dataset, out / key, out / "cache", max_detections,
                                  refiner=refiner)
        figures[key] = adapt.figures(summary)
    return {**figures, "default_refiner": str(current)}


def diagnostic(run: pathlib.Path, records: pathlib.Path) -> dict:
    """The run's best checkpoint on held-out refiner records (``train.eval_refiner``)."""
    from train.eval_refiner import evaluate_run

    figures = evaluate_run(run, data_dir=records)
    return {k.removeprefix("eval/"): v for k, v in figures.items()}


def _row(name: str, f: dict) -> str:
    return (f"| {name} | **{f['pose_ap']:.3f}** | {f['pose_ap_mm']:.3f} | {f['pose_ap_mssd']:.3f} "
            f"| {f['pose_ap_mspd']:.3f} | {f['segm_ap']:.3f} | {f['pose_ap_initial']:.3f} |")


def card(name: str, run: pathlib.Path, result: dict, command: str) -> str:
    """``MODEL_CARD.md`` of a shipped refiner, from its run and the check's figures."""
    from threept_jax.data.run_dir import RunDir

    rd = RunDir(run, model="refiner")
    config, model = rd.read_config(), rd.read_model_config()
    steps = rd.checkpoint_steps()
    stem = model.pretrained_stem
    if stem != "none" and model.stem_descriptors:
        stem += " (descriptors start as its features: stem_descriptors)"
    a, b = result["candidate"], result["default"]
    lines = [
        f"# refiner-{name}: 3PT-R, shipped by `python -m train.ship` "
        f"({datetime.date.today().isoformat()})",
        "",
        "The refiner that `infer.load()`, `python -m infer bop|images|track` without "
        "`--refiner` and the demo use (`models/shipped.json`). It replaced "
        f"`{result['default_refiner']}` after refining the held-out scenes below better.",
        "",
        "## What it is",
        "",
        f"- 3PT-R (docs/refiner.md), `{model.variant}`, {model.crop_size} px crops, "
        f"{model.output_size} px maps, pretrained stem: {stem}.",
        f"- Trained by `python train/launch.py` (`config.json` here): {steps[-1] if steps else 0} "
        f"of {config.get('total_steps', '?')} planned steps; this folder holds the best "
        f"checkpoint, step {rd.best_step()}.",
        f"- Training records: `{config.get('data_dir', '?')}`.",
        "",
        "## Held-out check (the real inference path)",
        "",
        "The same detections (the default detector, every part of the dataset queried), "
        "refined by this model and by the refiner it replaced; BOP figures of the dataset's "
        "`val_pbr` images:",
        "",
        "    " + command,
        "",
        "| refiner | BOP 6D AP | AP-mm | AP MSSD | AP MSPD | segm AP | 6D AP before refinement |",
        "|---|---|---|---|---|---|---|",
        _row(f"this model (refiner-{name})", a),
        _row(f"the default it replaced (`{result['default_refiner']}`)", b),
        "",
        f"Box AP50 of the detections: {a['box_ap50']:.3f}.",
    ]
    if "records" in result:
        d = result["records"]
        # train.eval_refiner reports the rotation after 1 and after its last step N.
        last = max((k for k in d if k.startswith("rot_deg_after_")),
                   key=lambda k: int(k.rsplit("_", 1)[1]))
        lines += [
            "",
            "## Diagnostic: held-out refiner records (`train.eval_refiner`)",
            "",
            f"On `{result['records_dir']}`: matches within 2 px {d['match_within_2px']:.3f} "
            f"against position alone {d['match_within_2px_same_place']:.3f}; median rotation "
            f"error {d['rot_deg_before']:.2f} -> {d[last]:.2f} degrees; MSSD recall "
            f"{d['ar_mssd_before']:.3f} -> {d['ar_mssd_after']:.3f} (before -> after its "
            f"{last.rsplit('_', 1)[1]} steps).",
        ]
    lines += [
        "",
        "## Limits",
        "",
        "Checked on one held-out dataset only; the figures above are all that was measured. "
        "Re-run the check on your own scenes before relying on it: `python -m train.ship` with "
        "`--dataset-dir` yours.",
        "",
    ]
    return "\n".join(lines)


def ship(run: pathlib.Path, name: str, result: dict, command: str) -> pathlib.Path:
    """Export ``run`` to ``models/refiner-NAME`` with its card and name it the shipped
    refiner (``models/shipped.json``). Returns the folder."""
    from infer import shipped
    from train import export

    folder = shipped.MODELS_DIR / f"refiner-{name}"
    existed = folder.exists()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "MODEL_CARD.md").write_text(card(name, run, result, command))  # export keeps it
        export.export(run, folder, model="refiner")
        shipped.set_shipped("refiner", folder.name)
    except BaseException:
        if not existed:
            shutil.rmtree(folder, ignore_errors=True)
        raise
    return folder


def main(argv: Sequence[str] | None = None) -> dict:
    args = parse_args(argv)
    command = "python -m train.ship " + shlex.join(sys.argv[1:] if argv is None else argv)
    result = check(args.run, args.dataset_dir, args.out, args.max_detections)
    if args.records is not None:
        result["records"] = diagnostic(args.run, args.records)
        result["records_dir"] = str(args.records)
    a, b = result["candidate"][DECIDES], result["default"][DECIDES]
    result["ships"] = a > b
    print(f"held-out BOP 6D AP on {args.dataset_dir}: {args.run} {a:.3f}, the default "
          f"({result['default_refiner']}) {b:.3f}", flush=True)
    if result["ships"]:
        result["shipped_as"] = str(ship(args.run, args.name, result, command))
        print(f"shipped as {result['shipped_as']}, the default refiner from now on "
              "(models/shipped.json; commit both to keep them)", flush=True)
    else:
        print("not shipped: it does not refine the held-out scenes better than the default; "
              "nothing under models/ changed", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ship_check.json").write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
