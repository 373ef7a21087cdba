"""The main job on built-in defaults: ``python -m demo`` (what ``make demo`` runs).

The ways 3PT is used, on full images, on a 2-core CPU in at most 15 minutes, with nothing
downloaded and nothing from outside the repository:

1. **Adapted** (``python -m train.adapt``, a user's own parts): five procedural parts of a fixed
   seed stand for the parts of a robot cell (one camera above a tray at a working distance,
   ``datagen/cell.py``; its depth range bounds the poses). Piles of them in the cell are
   path-traced (Mitsuba, 640x480, 2 samples per pixel denoised) and packed, the dense cell
   detector (``train.cell_detector``: the five parts at every place of full images) is trained
   from scratch for ``--minutes`` (5; ``--detector 3pt``: 3PT-D, a ``--config`` detector from
   scratch or ``--from shipped``), and with ``--refiner-minutes`` (default 0: none) a refiner
   (3PT-R, ``train/configs/refiner.py:tiny``) on the same records; for the cell detector the
   templates' score is then calibrated per part on the training images (what setting 3 uses
   too). The detector finds every part of the cell in new test scenes (also a part the test
   images do not show), each box is posed by its part's templates fitted inside it (3PT-D:
   object generation) and the refiner refines it (the trained 3PT-R when its held-out check passes,
   else the training-free contour refiner): box AP50, and BOP 6D AP, AP-mm and segmentation AP
   before refinement and after it.
2. **No training** (``--detector templates``): the same cell, the same test images, its parts
   found from their CAD models alone (``infer/shape_detect.py``: selective-search proposals,
   contour templates fitted to each, the best poses verified by the contour refiner, scored
   by the shared score and the shipped verifier, both fitted on cells of other parts), then
   refined by the contour refiner. The baseline every learned detector must beat.
3. **No training, score calibrated on the cell** (``python -m train.templates_score --cell``):
   the templates detector again, its score a logistic model per part fitted on the adapted
   setting's first 30 training images (what a right candidate of each part looks like; no
   network is trained; the verifier corrects it), on the same test images. Settings 1-4 look
   at the same images with the same parts, so the templates detector searches each image once
   (:func:`infer.shape_detect.shared_searches`) and each setting scores what it found its own
   way: the BOP ``time`` of settings 2 and 3 leaves the search out (``bench/shape_search.py``
   times it).
4. **No training, two calibrated views**: the same test images, each scene's two images (two
   shots of the same tray from known camera poses: a second camera, or an eye-in-hand camera
   moved by the robot) as one calibrated capture (``python -m infer bop --targets
   multiview``): the templates detector searches each image (the search of setting 2, shared),
   a part's detections are matched across the two views and moved to their centres' fusion
   (:func:`infer.scene.fuse_posed_views`), and the contour refiner refines them in both views.
   One view sees a part's depth only through its outline's size.
5. **Zero-shot**: five other procedural parts, never seen in training, are onboarded from
   their meshes alone and detected by the shipped models, as a user who installs threept_jax
   gets them, in a cell of their own (val scenes choose the overlay threshold, test scenes give
   the figures), and refined by the shipped refiner when one ships, else by the contour
   refiner.

A refiner trained for a few CPU minutes has not improved the poses yet (the 1.5 minutes the
demo gave it until 2026-11-29 never did), so none is trained by default; with
``--refiner-minutes`` its held-out figures (rotation error and MSSD recall before and after its
steps) are printed, and a refiner that does not make held-out poses better is not used
(``train.adapt.refiner_helps``): the contour refiner refines instead. The "before" and
"after" figures say which way refinement went. Every stage resumes: run the same command again and finished stages are
skipped (a killed data generation redoes only its unfinished scene, a killed training restarts
from its last checkpoint). Outputs go to ``--out`` (default ``runs/demo``): ``report.json``,
the settings' overlays (``adapted/test/overlays``, ``no_training/test/overlays``,
``calibrated/test/overlays``, ``two_views/test/overlays``, ``zero_shot/test/overlays``: boxes, the
contours of the refined poses in colour and of the poses before refinement in white, at least
640 px wide, only detections above the best-F1
threshold of the val scenes). What 2 cores reach in these minutes, and the curve of AP against
training time, are in docs/limits.md and docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time
from collections.abc import Sequence

#: The demo's parts: ``procedural:5`` of these seeds (adapted, zero-shot).
ADAPTED_SEED, ZERO_SHOT_SEED = 7, 8


def zero_shot(out: pathlib.Path, test_scenes: int, seed: int) -> dict:
    """Scenes of parts the shipped models never saw (val and test shards), detected by them
    and refined by the default refiner (the shipped 3PT-R when one ships, else the contour
    refiner)."""
    from infer.shipped import default_refiner, shipped
    from train import adapt

    args = adapt.parse_args(["--meshes", "procedural:5", "--seed", str(seed), "--workdir",
                             str(out), "--test-scenes", str(test_scenes), "--from", "scratch"])
    adapt.generate(args, out / "data", sets=("val", "test"))
    return adapt.test(shipped("detector"), out / "data", out, out / "cache", overlays=6,
                      instances=args.instances, refiner=default_refiner())


def no_training(adapted_dir: pathlib.Path, out: pathlib.Path) -> dict:
    """The adapted setting's val and test scenes (the cell's parts), detected by the
    training-free templates detector and refined by the contour refiner (the parts' contour
    models from the adapted setting's cache)."""
    from infer.shipped import CONTOUR
    from train import adapt

    return adapt.test(None, adapted_dir / "data", out, adapted_dir / "cache", overlays=6,
                      instances=adapt.INSTANCES, refiner=CONTOUR)


def calibrated(adapted_dir: pathlib.Path, out: pathlib.Path) -> dict:
    """The no-training setting with the templates detector's score calibrated on the cell: a
    logistic model per part fitted on the adapted setting's first training images (the one
    ``train.adapt`` fitted for the cell detector, ``adapted_dir/templates_score.json``, else
    fitted here and written there: :func:`train.adapt.calibrate`; no network), detections
    refined by the contour refiner (the parts' contour models from the adapted setting's
    cache)."""
    from infer.shipped import CONTOUR
    from train import adapt

    cache = adapted_dir / "cache"
    path = adapt.calibrate(adapted_dir / "data" / "train", adapted_dir / adapt.SCORE_FILE,
                           cache)
    return adapt.test(None, adapted_dir / "data", out, cache, overlays=6,
                      instances=adapt.INSTANCES, refiner=CONTOUR, templates_score=path)


def write_captures(data: pathlib.Path) -> None:
    """Writes ``data/test_targets_multiview_bop25.json``: each scene of ``data``'s ``val_pbr``
    split, all its images, as one multi-view group (what ``--targets multiview`` runs)."""
    from threept_jax.data import bop

    split = bop.BopDataset(data).split("val_pbr")
    bop.write_multiview_targets(data / bop.MULTIVIEW_TARGETS_FILE, [
        bop.MultiviewTarget(s, tuple((None, i) for i in split.scene(s).image_ids))
        for s in split.scene_ids])


def two_views(adapted_dir: pathlib.Path, out: pathlib.Path, threshold: float) -> dict:
    """The no-training setting on the test scenes' two images as one calibrated capture each
    (their cameras' ``cam_R_w2c``/``cam_t_w2c``; the groups written to the test data's
    ``test_targets_multiview_bop25.json``), refined by the contour refiner in both views;
    overlays above ``threshold`` (the no-training setting's, from its val scenes)."""
    from infer.shipped import CONTOUR
    from train import adapt

    data = adapted_dir / "data" / "test"
    write_captures(data)
    result = adapt.figures(adapt.infer_bop(
        None, data, out / "test", adapted_dir / "cache", adapt.max_detections(adapt.INSTANCES),
        overlays=6, overlay_threshold=threshold, refiner=CONTOUR, targets="multiview"))
    return {"test": result, "overlay_threshold": threshold, "refiner": CONTOUR,
            "overlays": str(out / "test" / "overlays")}


def summary(name: str, figs: dict) -> list[str]:
    """One setting's printed lines: box AP, then 6D AP, AP-mm and segmentation AP (before and
    after refinement when refining, :func:`train.adapt.summary_lines`)."""
    from train.adapt import summary_lines

    return [f"{name}: box AP50 {figs['box_ap50']:.3f}, AP {figs['box_ap']:.3f}",
            *(f"    {line}" for line in summary_lines(figs))]


def main(argv: Sequence[str] | None = None) -> dict:
    from train.adapt import DETECTORS
    from train.stages import CONFIGS, log_friendly_progress

    log_friendly_progress()

    p = argparse.ArgumentParser(prog="python -m demo", description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/demo"))
    p.add_argument("--minutes", type=float, default=5.0,
                   help="the detector's training budget: 5 keeps the demo within 15 minutes; "
                        "the cell detector needs about 10 on 2 cores to be useful (test box "
                        "AP50 0.52-0.68 at 10, 0.16-0.22 at 3.5-5; docs/training.md)")
    p.add_argument("--detector", default=DETECTORS[0], choices=DETECTORS,
                   help="the adapted setting's detector (train.adapt --detector): the dense "
                        "cell detector, or 3PT-D")
    p.add_argument("--from", dest="init_from", default="scratch", metavar="RUN|shipped|scratch",
                   help="with --detector 3pt (train.adapt --from): scratch trains a --config "
                        "detector in --minutes; shipped fine-tunes the shipped one (its larger "
                        "network takes fewer steps in the same minutes)")
    p.add_argument("--config", default="tiny", choices=CONFIGS,
                   help="with --detector 3pt and --from scratch: the 3PT-D config (tiny: the "
                        "most steps in a few minutes)")
    p.add_argument("--refiner-minutes", type=float, default=0.0,
                   help="3PT-R training budget (0: none, the default: a 3PT-R of a few CPU "
                        "minutes has never passed its held-out check; the contour refiner "
                        "refines)")
    p.add_argument("--train-scenes", type=int, default=60, help="one image each (a cell)")
    p.add_argument("--test-scenes", type=int, default=4, help="2 images each, per setting")
    args = p.parse_args(argv)
    total = time.perf_counter()
    from infer.shape_detect import shared_searches
    from train import adapt

    # The first four settings look at the same images with the same parts: the templates
    # detector searches each image once (in the cell detector's test), and the shared score
    # and the cell's calibration score the same candidates.
    with shared_searches():
        adapted = adapt.main([
            "--meshes", "procedural:5", "--seed", str(ADAPTED_SEED), "--workdir",
            str(args.out / "adapted"), "--minutes", f"{args.minutes:g}", "--detector",
            args.detector, "--config", args.config, "--from", args.init_from,
            "--train-scenes", str(args.train_scenes), "--test-scenes", str(args.test_scenes),
            "--refiner-minutes", f"{args.refiner_minutes:g}"])

        print(f"\n== no training: the templates detector on the same cell and test images -> "
              f"{args.out / 'no_training'}", flush=True)
        start = time.perf_counter()
        templates = no_training(args.out / "adapted", args.out / "no_training")
        print(f"   ({time.perf_counter() - start:.0f} s)")

        print(f"\n== no training, score calibrated on the cell: the templates detector, a score "
              f"per part fitted on the adapted setting's training images -> "
              f"{args.out / 'calibrated'}", flush=True)
        start = time.perf_counter()
        tuned = calibrated(args.out / "adapted", args.out / "calibrated")
        print(f"   ({time.perf_counter() - start:.0f} s)")

        print(f"\n== no training, two calibrated views: each test scene's two images as one "
              f"capture -> {args.out / 'two_views'}", flush=True)
        start = time.perf_counter()
        rig = two_views(args.out / "adapted", args.out / "two_views",
                        templates["overlay_threshold"])
        print(f"   ({time.perf_counter() - start:.0f} s)")

    print(f"\n== zero-shot: the shipped models on 5 parts never seen in training -> "
          f"{args.out / 'zero_shot'}", flush=True)
    start = time.perf_counter()
    unseen = zero_shot(args.out / "zero_shot", args.test_scenes, ZERO_SHOT_SEED)
    print(f"   ({time.perf_counter() - start:.0f} s)")

    report = {"adapted": adapted, "no_training": templates, "calibrated": tuned,
              "two_views": rig, "zero_shot": unseen,
              "minutes": (time.perf_counter() - total) / 60}
    (args.out / "report.json").write_text(json.dumps(report, indent=1, default=float))
    from train.adapt import refiner_lines

    lines = [*summary("adapted (trained on these 5 parts)", adapted["test"]),
             *(f"    {line}" for line in refiner_lines(adapted.get("refiner_heldout") or {})),
             *(["    the trained refiner is not used (it does not make held-out poses better): the "
                "contour refiner refines instead"]
               if adapted.get("refiner_trained") not in (None, adapted["refiner"]) else []),
             *summary("no training (templates detector and its verifier + contour refiner, "
                      "same images)", templates["test"]),
             *summary("no training, score calibrated on the cell (a score per part fitted on "
                      "30 training images, and the verifier; same images)", tuned["test"]),
             *summary("no training, two calibrated views (the same images, each scene's two "
                      "as one capture)", rig["test"]),
             *summary("zero-shot (the shipped models, 5 parts never seen)", unseen["test"])]
    print(f"\ndone in {report['minutes']:.1f} min. Full images, all parts queried, new scenes:\n"
          + "\n".join(f"  {line}" for line in lines)
          + f"\nReport {args.out / 'report.json'}; overlays {adapted['overlays']}, "
          f"{templates['overlays']}, {tuned['overlays']}, {rig['overlays']} and "
          f"{unseen['overlays']}")
    return report


if __name__ == "__main__":
    main()
