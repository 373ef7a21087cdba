"""The pretrained stems (issue 40), XFeat and ALIKED: seconds of one forward pass over a
refinement's crops, cold (compilation) and warm, at the crop sizes the issue's matching
measurement compared (64, 128 and 256 px), against 3PT-R's own encoder (the ``tiny`` refiner's
ViT on its 64 px crops, the reference) in the same process.

A refinement step encodes each instance's real crop and its 5 hypotheses' renders: ``--crops``
images (default 48: 8 instances x 6). The weights are the converted ones of ``models/xfeat``
and ``models/aliked`` (``scripts/convert_xfeat.py``, ``scripts/convert_aliked.py``).

``--records DIR`` (a refiner records folder, e.g. the demo's ``runs/demo/adapted/records``)
adds the matching measurement: each network's descriptors matched directly (untrained:
:class:`threept_jax.models.xfeat.XFeatDescriptors`, XFeat's stride-8 features;
:class:`threept_jax.models.aliked.ALIKEDDescriptors`, ALIKED's SDDH descriptors at each map
pixel, and its dense feature map as ``aliked-dense``) through the refiner's own held-out
evaluation (``train.eval_refiner.RefinerEvaluator``: the records' val split, the refinement
step's reciprocal matches of render edge pixels, PnP and the safe updates) at each crop size,
against matching by position alone in the same evaluation
(``eval/match_within_2px_same_place``), with the median rotation error and MSSD recall before
and after the step. The tolerance is 2 crop pixels at every size (the evaluator's), so a larger
crop is judged more strictly.

    python bench/stems.py [--stems xfeat aliked] [--crops 48] [--sizes 64 128 256]
        [--repeats 5] [--records DIR --split val --examples 32]
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
from flax import nnx  # noqa: E402
from flops import cold_and_warm  # noqa: E402

from threept_jax.data.pretrained import STEMS, stem_params  # noqa: E402
from threept_jax.models.aliked import ALIKEDDescriptors  # noqa: E402
from threept_jax.models.refiner import Refiner  # noqa: E402
from threept_jax.models.xfeat import XFeat, XFeatDescriptors  # noqa: E402
from train.configs import refiner as refiner_configs  # noqa: E402
from train.run_config import model_config  # noqa: E402


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--stems", nargs="+", default=sorted(STEMS), choices=sorted(STEMS))
    p.add_argument("--crops", type=int, default=48)
    p.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--records", type=pathlib.Path, default=None,
                   help="refiner records: also measure held-out matching")
    p.add_argument("--examples", type=int, default=32, help="instances matched")
    p.add_argument("--split", default="val", help="the records' split matched (the "
                   "networks never trained on any of them)")
    args = p.parse_args(argv)
    if args.records is not None and not (args.records / "objects.json").exists():
        sys.exit(f"{args.records} is not a records folder (no objects.json): pass the records "
                 "of a refiner or adaptation run, e.g. runs/demo/adapted/records (make demo)")
    key = jax.random.key(0)

    # First, while nothing is compiled: the stem's cold load (a refiner training's start) against
    # what it no longer does, a random initialisation of XFeat and its folded copy op by op.
    t = time.perf_counter()
    jax.block_until_ready(stem_params("xfeat"))
    load_s = time.perf_counter() - t
    t = time.perf_counter()
    for folded in (False, True):
        jax.block_until_ready(nnx.state(XFeat(folded=folded, rngs=nnx.Rngs(0))))
    init_s = time.perf_counter() - t
    print(f"stem_params('xfeat') cold {load_s:.2f} s; XFeat and its folded copy initialised at "
          f"random op by op (the reference: what loading no longer does) {init_s:.2f} s: "
          f"{load_s / init_s:.2f} x")

    cfg = model_config(refiner_configs.get_config("tiny"))
    refiner = Refiner(cfg, rngs=nnx.Rngs(0))
    encode = nnx.jit(lambda m, x: m.encoder(x, layers=cfg.encoder_hooks[:3])["patch_tokens"])
    images = jax.random.uniform(key, (args.crops, cfg.crop_size, cfg.crop_size, 3))
    ref_cold, ref_warm = cold_and_warm(
        lambda: encode(refiner, images).block_until_ready(), args.repeats)
    print(f"3PT-R tiny encoder, {args.crops} crops of {cfg.crop_size} px (reference): cold "
          f"{ref_cold:.2f} s, warm {ref_warm * 1e3:.1f} ms")
    result = {"reference": {"crop": cfg.crop_size, "cold_s": ref_cold, "warm_s": ref_warm},
              "stem_load": {"cold_s": load_s, "random_init_s": init_s}}

    forward = nnx.jit(lambda m, x: m(x)["features"])
    for name in args.stems:
        net = STEMS[name][0](ROOT / "models" / name)
        for size in args.sizes:
            images = jax.random.uniform(key, (args.crops, size, size, 3))
            cold, warm = cold_and_warm(lambda x=images, n=net: forward(n, x).block_until_ready(),
                                       args.repeats)
            print(f"{name}, {args.crops} crops of {size} px: cold {cold:.2f} s, warm "
                  f"{warm * 1e3:.1f} ms = {warm / ref_warm:.2f} x the reference")
            result[f"{name}/{size}"] = {"cold_s": cold, "warm_s": warm, "ratio": warm / ref_warm}
        if args.records is not None:
            kinds = {"xfeat": [("xfeat", lambda n, h: XFeatDescriptors(n, output_size=h))],
                     "aliked": [("aliked", lambda n, h: ALIKEDDescriptors(n, h)),
                                ("aliked-dense",
                                 lambda n, h: ALIKEDDescriptors(n, h, sddh=False))]}[name]
            for label, make in kinds:
                for size in args.sizes:
                    result.setdefault(f"{label}/{size}", {})["matching"] = matching(
                        make(net, 32), label, args.records, args.split, size, args.examples)
    return result


def matching(descriptors: nnx.Module, label: str, records: pathlib.Path, split: str, size: int,
             examples: int) -> dict:
    """The refiner's held-out evaluation of ``descriptors`` (a network's, matched directly, on
    a 32 x 32 map) at ``size`` px crops (module docstring)."""
    from train import sharding
    from train.eval_refiner import RefinerEvaluator

    c = refiner_configs.get_config("tiny")
    c.data_dir = str(records)
    c.model.update(crop_size=size, output_size=32)
    c.eval.update(split=split, num_examples=examples, batch_size=min(8, examples), num_steps=1)
    graphdef, params = nnx.split(descriptors)
    mesh = sharding.make_mesh(1, 1, jax.devices()[:1])
    out = RefinerEvaluator(c, graphdef, mesh)(nnx.to_pure_dict(params))
    keys = ("match_within_2px", "match_within_2px_same_place", "rot_deg_before",
            "rot_deg_after_1", "ar_mssd_before", "ar_mssd_after", "num_instances")
    figures = {k: out[f"eval/{k}"] for k in keys}
    print(f"{label} matched directly, {size} px crops, {int(figures['num_instances'])} {split} "
          f"instances: matches within 2 px {figures['match_within_2px']:.3f}, position alone "
          f"{figures['match_within_2px_same_place']:.3f}; median rotation error "
          f"{figures['rot_deg_before']:.2f} -> {figures['rot_deg_after_1']:.2f} deg, MSSD "
          f"recall {figures['ar_mssd_before']:.3f} -> {figures['ar_mssd_after']:.3f} (one step)")
    return figures


if __name__ == "__main__":
    main()
