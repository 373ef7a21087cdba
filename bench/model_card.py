"""The held-out figures of a model card (issue 26): a detector (the shipped one by default), and a
refiner when one is given or ships, on parts it never saw, as a user meets them: full images,
every part of the setting queried, ``python -m infer bop --evaluate`` (score threshold 0, the
best detections of each image kept: ``train.adapt.infer_bop``).

1. **held-out procedural parts in cell scenes**: the campaign's own held-out cell scenes
   (``W/data/cell``, ``val_pbr``: parts no training scene used), every part that appears in
   them queried in every image; and again with each image queried with the parts it shows
   (its BOP19 targets, written from the ground truth: instances at least 10 % visible), the
   BOP 6D localisation task and a robot cell that knows which parts are in the tray: the gap
   between the two is the cost of telling the queried parts apart;
2. **BOP meshes in cell scenes**: CAD models of ``../shared/meshes`` (MVTec ITODD and T-LESS
   industrial parts, never trained on) in cell scenes made here (``datagen --layout cell``,
   seeded: the same images on every machine), every part queried.

Printed per setting: box AP50 and AP, BOP 6D AP (object generation alone, and after
refinement with a refiner), AP-MSSD, AP-MSPD, and the seconds it took (``card.json`` in
``--out``); and a diagnostic, never the headline: the share of ground-truth instances (at least
10 % visible) that some kept detection covers at IoU >= 0.5 whatever its object, beside the same
share counting only detections of the right object: it tells a detector that finds parts but
not which part from one that does not find them. ``--detector`` takes any run or model, so
the same command measures another detector (a scratch one, an earlier checkpoint) on the same
images.

    python bench/model_card.py --campaign runs/campaign [--detector models/detector-cpu]
        [--refiner RUN] [--bop-scenes 8] [--out runs/card]
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from infer.shipped import shipped  # noqa: E402
from threept_jax.data import bop  # noqa: E402
from threept_jax.data.bop import write_targets  # noqa: E402
from threept_jax.eval.bop6d import gt_coverage, gt_targets  # noqa: E402
from train import adapt  # noqa: E402

SHARED = ROOT.parent / "shared" / "meshes" / "bop"
#: The BOP parts of setting 2: industrial, texture-less, in mm.
BOP_PARTS = [SHARED / "itodd" / "models" / f"obj_{i:06d}.ply" for i in (1, 2, 3, 4)] + [
    SHARED / "tless" / "models" / f"obj_{i:06d}.ply" for i in (5, 18)]


def bop_folder(out: pathlib.Path) -> pathlib.Path:
    """A BOP models folder of :data:`BOP_PARTS` (copies, with their ``models_info.json``
    entries: symmetries and diameters), as datagen reads one."""
    import shutil

    out.mkdir(parents=True, exist_ok=True)
    info = {}
    for path in BOP_PARTS:
        shutil.copy2(path, out / path.name)
        obj = str(int(path.stem.split("_")[1]))
        info[obj] = json.loads((path.parent / "models_info.json").read_text())[obj]
    (out / "models_info.json").write_text(json.dumps(info, indent=1))
    return out


def heldout_ids(dataset: pathlib.Path) -> list[int]:
    """The parts that appear in ``dataset``'s ``val_pbr`` ground truth."""
    ids = set()
    for gt in sorted((dataset / "val_pbr").glob("*/scene_gt.json")):
        for entries in json.loads(gt.read_text()).values():
            ids |= {int(e["obj_id"]) for e in entries}
    return sorted(ids)


def covered(dataset: pathlib.Path, results: pathlib.Path) -> tuple[float, float]:
    """(share of GT instances >= 10 % visible covered at IoU >= 0.5 by a detection of any
    object, by a detection of their own object) over ``dataset``'s ``val_pbr`` images
    (``threept_jax.eval.bop6d.gt_coverage``)."""
    hit_any, hit_own, total = gt_coverage(bop.BopDataset(dataset).split("val_pbr"),
                                          json.loads(results.read_text()))
    return hit_any / max(total, 1), hit_own / max(total, 1)


def results_json(out: pathlib.Path) -> pathlib.Path:
    """The 2D results ``python -m infer bop`` wrote in ``out`` (after refinement when refined)."""
    return next(out.glob("threept_*-val_pbr.json"))


def line(name: str, figs: dict, seconds: float) -> str:
    pose = (f"6D AP {figs['pose_ap_initial']:.3f} -> {figs['pose_ap']:.3f} refined"
            if "pose_ap_initial" in figs else f"6D AP {figs['pose_ap']:.3f} (object generation)")
    return (f"{name}: box AP50 {figs['box_ap50']:.3f}, AP {figs['box_ap']:.3f}; {pose}, "
            f"AP-MSSD {figs['pose_ap_mssd']:.3f}, AP-MSPD {figs['pose_ap_mspd']:.3f} "
            f"({seconds:.0f} s); diagnostic: GT covered at IoU 0.5 by any part's detection "
            f"{figs['covered_any']:.3f}, by its own part's {figs['covered_own']:.3f}")


def main(argv=None) -> dict:
    from train.stages import log_friendly_progress

    log_friendly_progress()
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--campaign", type=pathlib.Path, required=True,
                   help="the campaign's --workdir (its held-out cell scenes)")
    p.add_argument("--detector", type=pathlib.Path, default=None,
                   help="a detector run or model (default: the shipped one)")
    p.add_argument("--refiner", type=pathlib.Path, default=None,
                   help="a refiner run or model (default: the shipped one, when one ships)")
    p.add_argument("--bop-scenes", type=int, default=8, help="setting 2: 2 images each")
    p.add_argument("--out", type=pathlib.Path, default=pathlib.Path("runs/card"))
    args = p.parse_args(argv)
    detector = args.detector or shipped("detector")
    refiner = args.refiner or shipped("refiner")
    plan = json.loads((args.campaign / "campaign.json").read_text())
    keep = adapt.max_detections(plan["data"]["instances"])
    cache = args.out / "cache"
    results = {"detector": str(detector), "refiner": None if refiner is None else str(refiner)}

    cell = args.campaign / "data" / "cell"
    ids = heldout_ids(cell)
    print(f"== 1. held-out procedural parts in cell scenes: {len(ids)} parts, {cell}/val_pbr")
    start = time.perf_counter()
    figs = adapt.figures(adapt.infer_bop(detector, cell, args.out / "procedural", cache, keep,
                                         overlays=4, refiner=refiner, obj_ids=ids))
    seconds = time.perf_counter() - start
    hit_any, hit_own = covered(cell, results_json(args.out / "procedural"))
    results["procedural"] = {**figs, "parts": len(ids), "seconds": seconds,
                             "covered_any": hit_any, "covered_own": hit_own}

    write_targets(cell / "test_targets_bop19.json", gt_targets(bop.BopDataset(cell).split("val_pbr")))
    print("\n== 1b. the same images, each queried with the parts it shows (BOP19 targets)")
    start = time.perf_counter()
    figs = adapt.figures(adapt.infer_bop(detector, cell, args.out / "procedural_targets", cache,
                                         keep, overlays=4, refiner=refiner, targets="bop19"))
    seconds = time.perf_counter() - start
    hit_any, hit_own = covered(cell, results_json(args.out / "procedural_targets"))
    results["procedural_targets"] = {**figs, "seconds": seconds, "covered_any": hit_any,
                                     "covered_own": hit_own}

    data = args.out / "bop_data"
    print(f"\n== 2. BOP meshes in cell scenes: {len(BOP_PARTS)} parts -> {data}")
    gen = adapt.parse_args(["--meshes", str(bop_folder(args.out / "bop_meshes")),
                            "--workdir", str(args.out),
                            "--test-scenes", str(args.bop_scenes), "--from", "scratch",
                            "--seed", "0"])
    adapt.generate(gen, data, sets=("test",))
    start = time.perf_counter()
    figs = adapt.figures(adapt.infer_bop(detector, data / "test", args.out / "bop", cache,
                                         adapt.max_detections(gen.instances), overlays=4,
                                         refiner=refiner))
    seconds = time.perf_counter() - start
    hit_any, hit_own = covered(data / "test", results_json(args.out / "bop"))
    results["bop"] = {**figs, "parts": len(BOP_PARTS), "seconds": seconds,
                      "covered_any": hit_any, "covered_own": hit_own}

    print(f"\n{detector}" + ("" if refiner is None else f" + {refiner}"))
    print("  " + line("held-out procedural parts, cell", results["procedural"],
                      results["procedural"]["seconds"]))
    print("  " + line("same images, each queried with its own parts (BOP19 targets)",
                      results["procedural_targets"], results["procedural_targets"]["seconds"]))
    print("  " + line("BOP meshes (ITODD, T-LESS), cell", results["bop"],
                      results["bop"]["seconds"]))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "card.json").write_text(json.dumps(results, indent=1, default=float))
    return results


if __name__ == "__main__":
    main()
