"""Adapt 3PT to your own parts: ``python -m train.adapt --meshes DIR --workdir W``.

3PT finds parts it has never seen (zero-shot). An industrial cell, though, handles a fixed set
of parts, and the best BOP-Industrial entries train a few minutes per part. This command does
that with our own data engine, in stages that each resume when the command is run again:

1. **Scenes** (``datagen.generate``): path-traced scenes of exactly the given meshes, by
   default in a robot cell (``--layout cell``: one camera above a tray at a working distance
   drawn once from the seed and the parts' sizes, distractors, random materials; the cell and
   its depth range go to ``W/data/*/cell.json``, and detection uses that depth range), in three
   disjoint sets of one mesh pool: ``W/data/train`` (training), ``W/data/val`` (checkpoint
   selection and the score threshold of the overlays) and ``W/data/test`` (the report;
   neither training nor selection sees it).
2. **Records** (``datagen.pack``): ArrayRecord shards -> ``W/records``, with render banks at
   the model's render size when 3PT-D trains (3PT-R and the cell detector read none).
3. **Detector training**, by default (``--detector cell``) the dense cell detector
   (``python -m train.cell_detector``: the cell's parts at every place of full images,
   mosaics; docs/training.md, "The dense cell detector") from scratch for ``--minutes``, its
   steps planned from its own measured step time -> ``W/cell``, a run that ``python -m infer
   images --workdir W/cell`` loads (its boxes posed by the templates' fit) and that resumes
   when killed. With ``--detector 3pt``, 3PT-D: the warm step time of each model trained here
   is measured once (a few compiled steps of a throw-away state) and the number of steps that
   fits its budget (``--minutes`` for the detector, ``--refiner-minutes`` for the refiner) is
   fixed in ``W/adapt.json``, so that a resumed run keeps its learning-rate schedule; then
   ``train.trainer_detector`` fine-tunes the shipped detector
   (``models/``, :mod:`infer.shipped`) by default, ``--from RUN``'s best checkpoint, or from
   scratch (``--from scratch``); fine-tuning keeps the model section of the run it starts
   from. ``W`` is then an ordinary run directory (``config.json``, ``checkpoints/``, ``tb/``):
   ``python -m infer images --workdir W`` loads it, and a killed run resumes from its last
   checkpoint.
   With the cell detector, the templates detector's score is then calibrated on the training
   scenes (``python -m train.templates_score --cell W/data/train``, :func:`calibrate`: a
   logistic model per part, about a minute) -> ``W/templates_score.json``: the test scores the
   cell detector's templates' poses and detections with it (docs/training.md, "Poses"). A cell
   too small to fit one (too few right and wrong candidates per part) keeps the shared score.
4. **Refiner training** (``train.trainer_refiner``, only with ``--refiner-minutes`` > 0; the
   default 0 trains none and the contour refiner refines the test): a 3PT-R run of
   ``--refiner-config`` (``train/configs/refiner.py``) from scratch on the same records ->
   ``W/refiner``, an ordinary refiner run (``python -m infer bop --refiner W/refiner``); its
   best checkpoint by the held-out MSSD recall after refinement on the val records. Its
   held-out figures (:func:`refiner_heldout`: rotation error and MSSD recall before and after
   its steps, score accuracy) are printed and reported; a refiner whose steps lower the
   held-out recall, or leaves it as it was, is not used for the test (:func:`refiner_helps`):
   the training-free contour refiner (``--refiner contour``) refines instead, as it does
   without ``--refiner-minutes``.
5. **Test** (found done when ``W/report.json`` tested the same scenes with the same best
   checkpoints and options): the cell detector, or 3PT-D's best checkpoint (by full-image
   AP50 on the val scenes), runs ``python -m infer bop`` on the val scenes, whose best-F1 score becomes the
   overlay threshold, then on
   the test scenes: full images, every part queried, the best detections of an image whatever
   their score (as many as a scene holds instances at most, :func:`max_detections`), refined
   by ``W/refiner`` when one was trained and helps, else by the contour refiner. Box AP / AP50
   (COCO, BOP ignore rule), segmentation AP and BOP 6D AP and AP-mm -> ``W/report.json``
   (:func:`figures`: before and after refinement); overlays (boxes, pose contours after
   refinement in colour and before it in white, at least 640 px wide) under
   ``W/test/overlays``.

``--meshes`` takes what ``datagen.generate`` takes: BOP models folders, trees of mesh files
(``--mesh-units`` when not mm), or ``procedural:N`` (N parts of ``--seed``; the demo's parts).
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
from collections.abc import Sequence

from train.stages import (
    CONFIGS,
    EVAL_SHARE,
    done,
    log_friendly_progress,
    measure_step_seconds,
    stage,
    train_to,
)

#: Evaluations and checkpoints over a run.
NUM_EVALS = 4
#: The detectors it trains (``--detector``), the default first.
DETECTORS = ("cell", "3pt")
#: Mean part instances per generated scene (``--instances``).
INSTANCES = 8
#: The templates' score calibrated on the training scenes, in the workdir (:func:`calibrate`).
SCORE_FILE = "templates_score.json"


def calibrate(train: pathlib.Path, path: pathlib.Path, cache: pathlib.Path) -> pathlib.Path:
    """The templates detector's score calibrated on the scenes of ``train`` (a BOP dataset
    folder, ``train.cell_score.calibrate_cell``) -> ``path``, written once and kept. A
    cell too small to fit one (too few right and wrong candidates of every part) gets a file
    without parts, which scores every part with the shared weights, and its reason; one line
    says so."""
    from threept_jax.data.files import atomic_write_json
    from threept_jax.pipeline.shape_search import FEATURES
    from train import cell_score

    if not path.exists():
        try:
            weights = cell_score.calibrate_cell(train, None, cache / "contours")
        except cell_score.TooFewCandidates as e:
            print(f"   no part calibrated ({e}): the templates' shared score is used",
                  flush=True)
            weights = {"features": [*FEATURES, "bias"], "parts": {}, "error": str(e)}
        atomic_write_json(path, weights, indent=1)
    return path


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m train.adapt", description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--meshes", nargs="+", required=True,
                   help="the parts: BOP models folders, trees of mesh files, or procedural:N")
    p.add_argument("--mesh-units", default="mm", choices=("mm", "cm", "m", "in"),
                   help="units of the mesh files")
    p.add_argument("--workdir", type=pathlib.Path, required=True,
                   help="run folder: data/, records/, the training run, refiner/, test/, "
                        "report.json")
    p.add_argument("--minutes", type=float, default=10.0,
                   help="detector training budget (wall clock); the cell detector on 2 CPU "
                        "cores: test box AP50 0.16-0.22 after 3.5-5 minutes, 0.52-0.68 after 10 "
                        "on the demo's cell (docs/training.md, 'The dense cell detector')")
    p.add_argument("--detector", default=DETECTORS[0], choices=DETECTORS,
                   help="cell: the dense cell detector (train.cell_detector: the cell's parts at "
                        "every place of full images), its boxes posed by the templates' fit; "
                        "3pt: 3PT-D (--from, --config)")
    p.add_argument("--from", dest="init_from", default="shipped", metavar="RUN|shipped|scratch",
                   help="the detector to fine-tune (a training run or exported model: its best "
                        "checkpoint), 'shipped' (models/, infer.shipped) or 'scratch'")
    p.add_argument("--config", default="cpu", choices=CONFIGS,
                   help="train/configs/detector.py config (ignored for the model with --from)")
    p.add_argument("--refiner-minutes", type=float, default=0.0,
                   help="refiner (3PT-R) training budget (wall clock) after the detector's; "
                        "0: no refiner, the test scores object generation alone")
    p.add_argument("--refiner-config", default="tiny", choices=CONFIGS,
                   help="train/configs/refiner.py config")
    p.add_argument("--train-scenes", type=int, default=160,
                   help="training scenes: one image each in a cell (a new pile costs about what "
                        "another capture of the same pile does, bench/datagen.py), 4 random "
                        "views each with --layout mixed")
    p.add_argument("--test-scenes", type=int, default=6,
                   help="2 images each, and as many val scenes")
    p.add_argument("--layout", default="cell", choices=("cell", "mixed"),
                   help="cell: one camera above a tray at a known working distance (detection "
                        "uses its depth range); mixed: random views of drops, floats and packs")
    p.add_argument("--resolution", type=int, nargs=2, default=(640, 480), metavar=("W", "H"))
    p.add_argument("--spp", type=int, default=2,
                   help="path-tracing samples per pixel, denoised (bench/datagen_quality.py: 2 "
                        "denoised samples are closer to the converged image than 32 raw ones)")
    p.add_argument("--instances", type=int, default=INSTANCES,
                   help="mean part instances per scene")
    p.add_argument("--seed", type=int, default=0, help="scenes (and procedural parts)")
    p.add_argument("--overlays", type=int, default=6, help="test overlays written")
    args = p.parse_args(argv)
    for name in ("train_scenes", "test_scenes", "spp", "instances"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if not 0 < args.minutes <= 24 * 60:
        p.error(f"--minutes must be in (0, 1440], got {args.minutes:g}")
    if not 0 <= args.refiner_minutes <= 24 * 60:
        p.error(f"--refiner-minutes must be in [0, 1440] (0: no refiner), got "
                f"{args.refiner_minutes:g}")
    if min(args.resolution) < 64:
        p.error(f"--resolution must be at least 64 x 64, got {args.resolution}")
    if args.init_from == "scratch":
        args.init_from = None
    elif args.init_from == "shipped":
        from infer.shipped import shipped
        from threept_jax.data.run_dir import ModelFileError

        try:
            args.init_from = shipped("detector")
        except ModelFileError as e:
            p.error(f"--from shipped: {e}")
    else:
        args.init_from = pathlib.Path(args.init_from)
    if args.init_from is not None and not (args.init_from / "detector.json").exists():
        p.error(f"--from {args.init_from} is not a detector training run (no detector.json); "
                "pass the --workdir of a train/launch.py or train.adapt run")
    return args


# --------------------------------------------------------------------------- stages 1-2


def check_meshes(args) -> None:
    """Read every mesh of ``--meshes`` before any work (no workdir is made before this passes).
    No usable mesh: SystemExit naming each file and what is wrong with it. Some unusable: one
    line per skipped file, the run goes on with the others (datagen's own repeats of those
    warnings are silenced). A mesh that loads but does not path-trace counts as unusable, its
    line naming the file and Mitsuba's cause (datagen skips it too)."""
    import warnings

    from datagen import generate as G
    from datagen import scene as S
    from datagen.meshes import MeshSkippedWarning

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", MeshSkippedWarning)
            pool = G.build_pool(args.meshes, args.seed, args.mesh_units)
            usable = [i for i in range(len(pool)) if pool.load(i) is not None]
    except ValueError as e:  # a missing folder, no mesh file at all
        raise SystemExit(f"error: --meshes: {e}") from None
    reasons = list(pool.skipped_reasons.values())  # each names its file
    unrenderable = S.render_problems(pool, usable)
    reasons += list(unrenderable.values())
    usable = [i for i in usable if i not in unrenderable]
    if not usable:
        raise SystemExit("error: no usable mesh in --meshes; fix or remove these files:\n  "
                         + "\n  ".join(reasons))
    if reasons:
        print(f"warning: skipping {len(reasons)} of {len(pool)} meshes, adapting to the "
              f"{len(usable)} others:\n  " + "\n  ".join(reasons), flush=True)
        warnings.filterwarnings("ignore", category=MeshSkippedWarning)


def generate(args, data: pathlib.Path, sets: Sequence[str] = ("train", "val", "test")) -> None:
    """Scenes of ``args.meshes``: ``train``, and ``val`` and ``test`` as the two shards of one
    held-out set (disjoint scenes of the same mesh pool)."""
    from datagen import generate as G

    common = ["--meshes", *args.meshes, "--mesh-units", args.mesh_units,
              "--resolution", *map(str, args.resolution), "--spp", str(args.spp),
              "--max-depth", "3", "--instances", str(args.instances), "--layout", args.layout,
              "--distinct", "1", str(min(args.instances, 6)), "--val-fraction", "0",
              "--seed", str(args.seed), "--quiet"]
    per_scene = "1" if args.layout == "cell" else "4"
    runs = {"train": ["--split", "train", "--num-scenes", str(args.train_scenes),
                      "--images-per-scene", per_scene]}
    for shard, name in enumerate(("val", "test")):
        runs[name] = ["--split", "val", "--num-scenes", str(2 * args.test_scenes),
                      "--images-per-scene", "2", "--num-shards", "2", "--shard", str(shard)]
    for name in sets:
        print(f"   {name}: {data / name}", flush=True)
        G.main(["--out", str(data / name), *runs[name], *common])
    share_models(data, sets)


def share_models(data: pathlib.Path, sets: Sequence[str]) -> None:
    """Every split of ``data`` lists the parts of all of them: the data engine writes the
    meshes its scenes show, and a few test scenes may not show every part of the cell, where
    a user queries them all (a part missing from the images still competes for them). A mesh a
    split lacks is copied from the first split that has it (its files ``obj_NNNNNN.*`` and its
    ``models_info.json`` entry)."""
    import shutil

    from threept_jax.data import bop

    folders = [data / n / "models" for n in sets
               if (data / n / "models" / "models_info.json").is_file()]
    infos = {f: bop.load_models_info(f / "models_info.json") for f in folders}
    first: dict[int, pathlib.Path] = {}
    for f in folders:
        for k in infos[f]:
            first.setdefault(k, f)
    for f in folders:
        missing = sorted(set(first) - set(infos[f]))
        for k in missing:
            for src in first[k].glob(f"obj_{k:06d}.*"):
                shutil.copy2(src, f / src.name)
        if missing:
            bop.write_models_info(f / "models_info.json", {
                **infos[f], **{k: infos[first[k]][k] for k in missing}})


def pack(data: pathlib.Path, records: pathlib.Path, render_size: int | None) -> None:
    """Records of the train and val scenes, with render banks at ``render_size`` (None: no
    banks, which only 3PT-D and 3PT-R read)."""
    from datagen import pack as Pk

    for name, folder in (("train", "train_pbr"), ("val", "val_pbr")):
        if (records / name / "index.json").exists():
            print(f"   {records / name} exists, skipped")
            continue
        # No --split-label: every part is trained on and evaluated.
        banks = (["--no-banks"] if render_size is None else
                 ["--bank-size", str(render_size), "--num-templates", "512"])
        Pk.main(["--scenes", str(data / name / folder), "--out", str(records), "--name", name,
                 *banks, "--quiet"])


# --------------------------------------------------------------------------- stages 3-5


#: The patch embedding of a detector adapted from scratch: early convolutions. At equal CPU
#: minutes on the demo's cell (10 minutes, 2 cores) they took full-image test box AP50 from
#: 0.008 to 0.055 (a second seed: 0.005 to 0.035; YOLOv8n from scratch: 0.183);
#: ``bench/adapt_pace.py``, docs/training.md "Adapted 3PT-D against a standard detector". The
#: configs themselves keep the plain ViT's.
SCRATCH_STEM = "conv"


def base_config(args, records: pathlib.Path):
    """The detector's training config: ``--config``'s, with the model of ``--from``'s run, or
    with :data:`SCRATCH_STEM` from scratch."""
    from threept_jax.data.run_dir import RunDir
    from train.configs.detector import get_config

    config = get_config(args.config)
    if args.init_from is None:
        config.model.stem = SCRATCH_STEM
    else:
        model = RunDir(args.init_from).read_model_config().to_dict()
        config.model.update({k: v for k, v in model.items() if k in config.model})
        config.init_from = str(args.init_from.resolve())
    config.data_dir = str(records.resolve())
    config.progress_bar = True
    return config


def refiner_config(args, records: pathlib.Path):
    """The refiner's training config: ``--refiner-config``'s on the same records (its held-out
    evaluation reads their val split: the val scenes' parts, other scenes)."""
    from train.configs.refiner import get_config

    config = get_config(args.refiner_config)
    config.data_dir = str(records.resolve())
    config.progress_bar = True
    return config


def plan(args, configs: dict, workdir: pathlib.Path) -> dict:
    """Steps of each model of ``configs`` ({"detector": config, "refiner": config}) that fit
    its budget, measured once and kept in ``W/adapt.json`` (one entry per model: ``steps``,
    ``step_seconds``, ``minutes``, ``config``); a model planned before keeps its entry."""
    path = workdir / "adapt.json"
    saved = json.loads(path.read_text()) if path.exists() else {}
    flags = {"detector": ("--minutes", args.minutes, args.config),
             "refiner": ("--refiner-minutes", args.refiner_minutes, args.refiner_config)}
    for name, config in configs.items():
        flag, minutes, config_name = flags[name]
        if name in saved:
            entry = saved[name]
            print(f"   {name}: {entry['steps']} steps ({entry['step_seconds']:.3f} s each), "
                  f"from {path}")
            if entry["minutes"] != minutes:
                print(f"   note: the {name} was planned for {entry['minutes']:g} minutes; {flag} "
                      f"{minutes:g} is ignored so that the resumed run keeps its schedule (use "
                      "a new --workdir to train with another budget)")
            continue
        step_s = measure_step_seconds(config)
        steps = max(NUM_EVALS, int(minutes * 60 * (1 - EVAL_SHARE) / step_s))
        saved[name] = {"steps": steps, "step_seconds": step_s, "minutes": minutes,
                       "config": config_name}
        print(f"   {name}: {step_s:.3f} s per step of batch {config.batch_size}: {steps} steps "
              f"in {minutes:g} minutes")
    saved.update(meshes=args.meshes, **{"from": None if args.init_from is None
                 else str(args.init_from)})
    workdir.mkdir(parents=True, exist_ok=True)
    text = json.dumps(saved, indent=1)
    if not path.exists() or path.read_text() != text:
        path.write_text(text)
    return saved


# --------------------------------------------------------------------------- stage 6


def max_detections(instances: int) -> int:
    """Detections kept per test image whatever their score (AP ranks them; every one is refined
    when refining): the most instances a scene of ``--instances`` holds (datagen draws the
    count uniformly in (1 +- spread) x ``instances``: 4 to 12 for the default 8). Fewer would
    cap the recall; more only adds low-ranked false positives, each refined at a cost (about a
    second per image per 20 instances on 2 CPU cores)."""
    from datagen.scene import SceneConfig

    return max(1, math.floor((1 + SceneConfig.instance_spread) * instances))


def infer_bop(workdir: pathlib.Path | None, dataset: pathlib.Path, out: pathlib.Path,
              cache: pathlib.Path, max_detections: int, overlays: int = 0,
              overlay_threshold: float | None = None, refiner: pathlib.Path | str | None = None,
              obj_ids: Sequence[int] = (), targets: str = "all",
              templates_score: pathlib.Path | None = None) -> dict:
    """``python -m infer bop --evaluate`` (``infer.bop_runner.run_bop``, called in this process)
    of the best detector checkpoint of ``workdir`` (None: the training-free templates detector,
    ``--detector templates``), its templates scored with the cell's calibration
    ``templates_score`` when given (the templates or the cell detector), and of ``refiner``
    when given (a run's best checkpoint or ``"contour"``), on ``dataset``'s ``val_pbr``
    images, the ``max_detections`` best detections of an image whatever their score; every
    object of the dataset queried, or ``obj_ids``; ``targets="bop19"``: each image queried
    with the objects of its BOP19 targets."""
    from infer.bop_runner import run_bop
    from infer.cli import bop_args

    detector = (dict(detector="templates") if workdir is None
                else dict(workdir=pathlib.Path(workdir), step="best", num_templates=512))
    return run_bop(bop_args(
        dataset, out, **detector, templates_score=templates_score, split="val_pbr",
        targets=targets, evaluate=True,
        score_threshold=0.0, max_detections=max_detections, overlays=overlays,
        cache_dir=pathlib.Path(cache), overlay_threshold=overlay_threshold,
        refiner=pathlib.Path("none" if refiner is None else str(refiner)),
        obj_ids=list(obj_ids) or None))


#: The figures of a result that refinement changes (:func:`figures`).
POSE_FIGURES = ("pose_ap", "pose_ap_mm", "pose_ap_mssd", "pose_ap_mspd", "segm_ap")


def _pose_figures(pose: dict, detection: dict, suffix: str = "") -> dict:
    values = (pose.get("ap"), pose.get("ap_mm"), pose.get("ap_mssd"), pose.get("ap_mspd"),
              detection.get("segm", {}).get("ap"))
    return {name + suffix: v for name, v in zip(POSE_FIGURES, values)}


def figures(result: dict) -> dict:
    """The headline numbers of an ``infer bop --evaluate`` result.

    ``box_*``: the detector's boxes (COCO AP, AP50, best F1 and its score threshold).
    :data:`POSE_FIGURES` (BOP 6D AP, AP-mm, AP-MSSD, AP-MSPD and 2D segmentation AP): the
    written results, i.e. after refinement when a refiner ran; then the same figures of object
    generation alone (the initial poses and their silhouette masks) are added with the suffix
    ``_initial``: before refinement.
    """
    refined = "pose_initial" in result
    detection = result.get("detection", {})
    # With a refiner the final boxes are the refined poses' projected models (amodal); the
    # initial file keeps the detector's: the box figures are the detector's.
    box = result.get("detection_initial" if refined else "detection", {}).get("bbox", {})
    out = {"box_ap": box.get("ap"), "box_ap50": box.get("ap50"), "box_f1": box.get("f1"),
           "box_f1_threshold": box.get("f1_threshold"),
           **_pose_figures(result.get("pose", {}), detection)}
    if refined:
        out.update(_pose_figures(result["pose_initial"], result.get("detection_initial", {}),
                                 "_initial"))
    return out


def summary_lines(figs: dict) -> list[str]:
    """The 6D and segmentation figures of :func:`figures` as printed lines: one without a
    refiner, "before refinement" and "after refinement" with one."""

    def line(suffix: str = "") -> str:
        return (f"6D AP {figs['pose_ap' + suffix]:.3f}, AP-mm {figs['pose_ap_mm' + suffix]:.3f}, "
                f"segm AP {figs['segm_ap' + suffix]:.3f}")

    if "pose_ap_initial" not in figs:
        return [f"object generation (no refiner): {line()}"]
    return [f"before refinement: {line('_initial')}", f"after refinement:  {line()}"]


def refiner_heldout(refiner: pathlib.Path) -> dict:
    """The refiner's held-out figures: its best checkpoint on its val records (the same parts
    in other scenes), ``eval/`` dropped. Training evaluated that checkpoint with
    :class:`train.eval_refiner.RefinerEvaluator` and saved the figures with it (``train_to``
    evaluates ``NUM_EVALS`` times); they are read back, not computed again (which would compile
    the evaluation a second time). A best checkpoint saved without them (a run stopped between
    evaluations) is evaluated now (:func:`train.eval_refiner.evaluate_run`)."""
    from threept_jax.data.run_dir import RunDir
    from train.eval_refiner import evaluate_run

    run = RunDir(refiner, model="refiner")
    step = run.best_step()
    saved = run.saved_metrics(step)
    held = {**saved, "step": step} if "eval/ar_mssd_after" in saved else \
        evaluate_run(refiner, step=step)
    return {k.removeprefix("eval/"): v for k, v in held.items() if k != "eval/time_s"}


def refiner_helps(h: dict) -> bool:
    """Whether the refiner's held-out figures (:func:`refiner_heldout`) earn it the test: its
    steps must raise the MSSD recall of the poses they start from. One that makes held-out
    poses worse (the rule inference warns by, :func:`infer.checkpoint.heldout_check`) would
    lose every user of it accuracy, and one that leaves them as they were (a few CPU minutes of
    training often does: the safe updates refuse its steps) is no better than the
    training-free contour refiner, which refines the test instead."""
    return h["ar_mssd_after"] > h["ar_mssd_before"]


def refiner_lines(h: dict) -> list[str]:
    """:func:`refiner_heldout`'s figures as printed lines: rotation error and MSSD AR before and
    after the refiner's steps, its matches within 2 px against matching by position alone (the
    baseline its descriptors must beat), and how often its score picks the best hypothesis
    (none without a refiner)."""
    if not h:
        return []
    steps = max(int(k.removeprefix("rot_deg_after_")) for k in h
                if k.startswith("rot_deg_after_"))
    after = f"rot_deg_after_{steps}"
    return [f"refiner, held-out crops ({h['num_instances']:.0f} instances x its hypotheses, "
            f"{steps} steps): median rotation error {h['rot_deg_before']:.1f} -> "
            f"{h[after]:.1f} deg, MSSD AR {h['ar_mssd_before']:.3f} -> {h['ar_mssd_after']:.3f}; "
            f"matches within 2 px {h['match_within_2px']:.2f} (position alone "
            f"{h['match_within_2px_same_place']:.2f}); score picks the best hypothesis "
            f"{h['score_acc']:.2f} of the time"]


def test(workdir: pathlib.Path | None, data: pathlib.Path, out: pathlib.Path,
         cache: pathlib.Path, overlays: int, instances: int,
         refiner: pathlib.Path | str | None = None,
         templates_score: pathlib.Path | None = None) -> dict:
    """The best checkpoint of ``workdir`` (None: the training-free templates detector; the
    templates scored with the cell's calibration ``templates_score`` when given) on ``data/val`` (whose best-F1
    score becomes the overlay threshold; detection alone, no refinement) and on ``data/test``,
    refined by ``refiner`` when given, scenes generated with ``--instances instances``:
    figures, threshold and the overlays' folder."""
    keep = max_detections(instances)
    val = figures(infer_bop(workdir, data / "val", out / "val", cache, keep,
                            templates_score=templates_score))
    threshold = val["box_f1_threshold"]
    print(f"   overlay threshold {threshold:.3f} (best F1 {val['box_f1']:.3f} on the val scenes)")
    result = figures(infer_bop(workdir, data / "test", out / "test", cache, keep,
                               overlays=overlays, overlay_threshold=threshold, refiner=refiner,
                               templates_score=templates_score))
    return {"test": result, "val": val, "overlay_threshold": threshold,
            "refiner": None if refiner is None else str(refiner),
            "overlays": str(out / "test" / "overlays")}


def inputs_of_test(workdir: pathlib.Path, data: pathlib.Path, refiner: pathlib.Path | str,
                   args: argparse.Namespace, templates_score: pathlib.Path | None = None
                   ) -> dict:
    """What the test stage's figures depend on: the val and test scenes, the detector's and
    the refiner's best checkpoints, and the options of the test."""
    from threept_jax.data import dense_run
    from threept_jax.data.run_dir import RunDir

    refiner_step = (None if isinstance(refiner, str) else
                    int(RunDir(refiner, model="refiner").best_step()))
    run_file = workdir / dense_run.RUN_FILE
    detector_step = (json.loads(run_file.read_text())["steps"] if run_file.is_file()
                     else int(RunDir(workdir).best_step()))
    scenes = {name: sorted(p.name for p in (data / name / "val_pbr").iterdir() if p.is_dir())
              for name in ("val", "test")}
    return {"scenes": scenes, "detector_step": detector_step,
            "refiner": str(refiner), "refiner_step": refiner_step, "overlays": args.overlays,
            "instances": args.instances,
            "templates_score": None if templates_score is None else str(templates_score)}


def tested(report_path: pathlib.Path, inputs: dict) -> dict | None:
    """The test figures of a finished run's report when it tested these ``inputs``
    (:func:`inputs_of_test`); None when the test must run (no report, or other inputs)."""
    if not report_path.exists():
        return None
    report = json.loads(report_path.read_text())
    if report.get("test_inputs") != inputs or (
            inputs["overlays"] and not pathlib.Path(report["overlays"]).is_dir()):
        return None
    print("   found done (report.json tested these checkpoints with these options)")
    return {k: report[k] for k in ("test", "val", "overlay_threshold", "refiner", "overlays")}


def main(argv: Sequence[str] | None = None) -> dict:
    from infer.shipped import CONTOUR

    log_friendly_progress()
    args = parse_args(argv)
    check_meshes(args)
    w = args.workdir
    data, records, cache = w / "data", w / "records", w / "cache"
    refiner = w / "refiner" if args.refiner_minutes > 0 else None
    use_refiner = refiner or CONTOUR
    n = 6 if refiner else 5
    minutes: dict[str, float] = {}

    start = stage(f"1/{n} scenes of {' '.join(args.meshes)} -> {data}")
    generate(args, data)
    minutes["scenes"] = done(start) / 60

    cell = args.detector == "cell"
    configs = {} if cell else {"detector": base_config(args, records)}
    if refiner:
        configs["refiner"] = refiner_config(args, records)
    start = stage(f"2/{n} records{'' if cell else ' and render banks'} -> {records}")
    pack(data, records, None if cell else int(configs["detector"].model.render_size))
    minutes["records"] = done(start) / 60

    if cell:
        from train import cell_detector

        # The cell detector plans its steps from its own measured step time.
        detector = w / "cell"
        start = stage(f"3/{n} cell detector training ({args.minutes:g} minutes, from scratch) "
                      f"-> {detector}")
        trained = cell_detector.train(records, detector, minutes=args.minutes, val=data / "val")
        steps = trained["steps"]
        minutes["training"] = done(start) / 60
        score_file = w / SCORE_FILE
        start = stage(f"4/{n} the templates' score calibrated on the training scenes -> "
                      f"{score_file}")
        score = calibrate(data / "train", score_file, cache)
        minutes["calibration"] = done(start) / 60
        budget = plan(args, configs, w) if refiner else {}
    else:
        detector, score = w, None
        budgets = ", ".join(f"the {c.model.variant} {name} in {m:g} minutes" for name, c, m in (
            ("detector", configs["detector"], args.minutes),
            ("refiner", configs.get("refiner"), args.refiner_minutes)) if c is not None)
        start = stage(f"3/{n} budget: steps of {budgets}")
        budget = plan(args, configs, w)
        minutes["budget"] = done(start) / 60

        steps = budget["detector"]["steps"]
        start = stage(f"4/{n} detector training ({steps} steps, "
                      f"{'from ' + str(args.init_from) if args.init_from else 'from scratch'}) "
                      f"-> {w}")
        train_to(configs["detector"], steps, w, evals=NUM_EVALS)
        minutes["training"] = done(start) / 60

    if refiner:
        start = stage(f"{n - 1}/{n} refiner training ({budget['refiner']['steps']} steps, from "
                       f"scratch) -> {refiner}")
        train_to(configs["refiner"], budget["refiner"]["steps"], refiner, evals=NUM_EVALS)
        minutes["refiner_training"] = done(start) / 60
        heldout = refiner_heldout(refiner)
        for line in refiner_lines(heldout):
            print(f"   {line}")
        if not refiner_helps(heldout):
            print("   the trained refiner does not make held-out poses better: the contour "
                  "refiner refines the test instead; train it longer (--refiner-minutes) or on "
                  "more parts", flush=True)
            use_refiner = CONTOUR
    elif "refiner" in budget:
        print(f"   note: --refiner-minutes 0: the refiner planned in {w / 'adapt.json'} is "
              "neither trained nor used")

    start = stage(f"{n}/{n} full-image test on new scenes -> {w / 'test'}"
                   + f", refined by {use_refiner}")
    inputs = inputs_of_test(detector, data, use_refiner, args, score)
    report = tested(w / "report.json", inputs)
    if report is None:
        report = test(detector, data, w, cache, args.overlays, args.instances,
                      refiner=use_refiner, templates_score=score)
    minutes["test"] = done(start) / 60
    report.update(steps=steps, detector=args.detector,
                  config="dense" if cell else configs["detector"].model.variant,
                  minutes=minutes, test_inputs=inputs)
    if refiner:
        report.update(refiner_steps=budget["refiner"]["steps"],
                      refiner_config=configs["refiner"].model.variant, refiner_heldout=heldout,
                      refiner_trained=str(refiner))
    (w / "report.json").write_text(json.dumps(report, indent=1, default=float))
    figs = report["test"]
    print("\nadapted detector, test scenes (full images, all parts queried): box AP50 "
          f"{figs['box_ap50']:.3f}, AP {figs['box_ap']:.3f}")
    for line in summary_lines(figs) + refiner_lines(report.get("refiner_heldout") or {}):
        print(f"  {line}")
    print(f"report {w / 'report.json'}, overlays {w / 'test' / 'overlays'}")
    return report


if __name__ == "__main__":
    main()
