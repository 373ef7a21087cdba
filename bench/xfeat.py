"""The pretrained XFeat stem (issue 40): seconds of one forward pass over a refinement's crops,
cold (compilation) and warm, at the crop sizes the issue's matching measurement compared
(64, 128 and 256 px), against 3PT-R's own encoder (the ``tiny`` refiner's ViT on its 64 px
crops, the reference) in the same process.

A refinement step encodes each instance's real crop and its 5 hypotheses' renders: ``--crops``
images (default 48: 8 instances x 6). XFeat's weights are the converted ones of
``models/xfeat`` (``scripts/convert_xfeat.py``).

    python bench/xfeat.py [--crops 48] [--sizes 64 128 256] [--repeats 5]
"""

from __future__ import annotations

import argparse
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
from flax import nnx  # noqa: E402
from flops import cold_and_warm  # noqa: E402

from threept_jax.data.pretrained import load_xfeat  # noqa: E402
from threept_jax.models.refiner import Refiner  # noqa: E402
from train.configs import refiner as refiner_configs  # noqa: E402
from train.run_config import model_config  # noqa: E402


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--crops", type=int, default=48)
    p.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args(argv)
    key = jax.random.key(0)

    cfg = model_config(refiner_configs.get_config("tiny"))
    refiner = Refiner(cfg, rngs=nnx.Rngs(0))
    encode = nnx.jit(lambda m, x: m.encoder(x, layers=cfg.encoder_hooks[:3])["patch_tokens"])
    images = jax.random.uniform(key, (args.crops, cfg.crop_size, cfg.crop_size, 3))
    ref_cold, ref_warm = cold_and_warm(
        lambda: encode(refiner, images).block_until_ready(), args.repeats)
    print(f"3PT-R tiny encoder, {args.crops} crops of {cfg.crop_size} px (reference): cold "
          f"{ref_cold:.2f} s, warm {ref_warm * 1e3:.1f} ms")
    result = {"reference": {"crop": cfg.crop_size, "cold_s": ref_cold, "warm_s": ref_warm}}

    xfeat = load_xfeat(ROOT / "models" / "xfeat")
    forward = nnx.jit(lambda m, x: m(x)["features"])
    for size in args.sizes:
        images = jax.random.uniform(key, (args.crops, size, size, 3))
        cold, warm = cold_and_warm(lambda x=images: forward(xfeat, x).block_until_ready(),
                                   args.repeats)
        print(f"XFeat, {args.crops} crops of {size} px ({size // 8} x {size // 8} features): "
              f"cold {cold:.2f} s, warm {warm * 1e3:.1f} ms = {warm / ref_warm:.2f} x the "
              f"reference")
        result[size] = {"cold_s": cold, "warm_s": warm, "ratio": warm / ref_warm}
    return result


if __name__ == "__main__":
    main()
