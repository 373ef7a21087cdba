"""Benchmark: image quality per second of the data generator's renders (issue 24).

Each row renders the same demo scenes (the robot cell of ``python -m train.adapt``'s defaults:
``procedural:5`` of the demo's seed, 640x480, about 8 parts and distractors in a tray) with
one setting of the path tracer and scores what datagen writes (its own auto exposure, 8-bit
sRGB) against what it would write from a converged render of the same scene and camera
(``--ref-spp`` samples per pixel, path length 6, no denoising: the reference run of the same
process). Settings: samples per pixel, path length (``max_depth``: 3 drops the light of
third and later bounces) and Open Image Denoise fed the albedo and normal of the same samples
(``threept_jax/render/denoise.py``).

Figures per row: PSNR (dB, over the 8-bit RGB) and SSIM (Wang et al. 2004, 11-pixel Gaussian
window, on the luma) against the reference, and seconds per image (path trace + denoise, warm:
the first render of each setting, which compiles Mitsuba's kernels, is reported as cold),
with the ratio of that time to the reference's. Higher PSNR for fewer seconds wins.

    python bench/datagen_quality.py [--scenes 3] [--ref-spp 256]
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import tempfile
import time

import cv2
import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from datagen import generate as G  # noqa: E402
from datagen import materials as Mt  # noqa: E402
from datagen import scene as S  # noqa: E402

#: (samples per pixel, path length, denoise): the settings compared.
SETTINGS = (
    (4, 3, False), (8, 3, False), (16, 3, False), (32, 3, False), (8, 6, False),
    (1, 3, True), (2, 3, True), (4, 3, True), (8, 3, True), (4, 6, True),
)
#: The demo's setting before this benchmark (``train.adapt``: 8 spp, path length 3, raw).
BASELINE = (8, 3, False)
KEY = 0.18  # exposure key of every row (datagen draws it per image; fixed here to compare)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0**2 / max(mse, 1e-12)))


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """Mean SSIM of the luma of two uint8 RGB images (Gaussian window, sigma 1.5)."""
    def luma(x):
        return cv2.cvtColor(x, cv2.COLOR_RGB2GRAY).astype(np.float64)

    x, y = luma(a), luma(b)
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2

    def blur(z):
        return cv2.GaussianBlur(z, (11, 11), 1.5)

    mx, my = blur(x), blur(y)
    vx, vy, cxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
    return float(s.mean())


def written(scene, K, T, hw, spp: int, depth: int, denoise: bool, seed: int):
    """What datagen writes for this setting (uint8 sRGB) and the seconds the render took."""
    scene.set_max_depth(depth)
    scene.render(K, T, hw, spp=1, seed=0, outputs=("rgb",), linear=True, denoise=denoise)
    t0 = time.perf_counter()  # the build (and its kernels) above is not the setting's cost
    rgb = scene.render(K, T, hw, spp=spp, seed=seed, outputs=("rgb",), linear=True,
                       denoise=denoise)["rgb"]
    seconds = time.perf_counter() - t0
    return Mt.to_uint8_srgb(Mt.auto_exposure(rgb, KEY)), seconds


def label(setting) -> str:
    spp, depth, den = setting
    return f"{spp} spp, depth {depth}" + (", OIDN" if den else "")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", type=int, default=3)
    p.add_argument("--ref-spp", type=int, default=256)
    p.add_argument("--seed", type=int, default=7, help="the demo's adapted parts and cell")
    p.add_argument("--save", type=pathlib.Path, default=None,
                   help="write a side-by-side crop of each row here (a JPEG) to look at")
    args = p.parse_args()

    pool = G.build_pool(["procedural:5"], args.seed)
    cell = G.design_cell(pool, args.seed, (640, 480))
    cfg = S.SceneConfig(resolution=(640, 480), spp=1, layout="cell", cell=cell, instances=8,
                        distinct=(1, 5), max_depth=3, denoise=False)
    rows: dict = {s: [] for s in SETTINGS}
    crops = []
    with tempfile.TemporaryDirectory() as tmp:
        assets = S.AssetCache(pool, pathlib.Path(tmp) / "models")
        for k in range(args.scenes):
            rng = np.random.default_rng(np.random.SeedSequence([args.seed, 24, k]))
            res = S.generate_scene(pathlib.Path(tmp) / f"{k:06d}", k, rng, assets,
                                   list(range(len(pool))), cfg)
            scene, K, T, hw = res.last_view
            ref, ref_s = written(scene, K, T, hw, args.ref_spp, 6, False, seed=k)
            print(f"scene {k}: reference {args.ref_spp} spp, depth 6: {ref_s:.1f} s")
            row_crops = [ref]
            for s in SETTINGS:
                img, sec = written(scene, K, T, hw, *s, seed=1000 + k)
                rows[s].append((psnr(img, ref), ssim(img, ref), sec, sec / ref_s))
                row_crops.append(img)
                print(f"  {label(s):24s} PSNR {rows[s][-1][0]:5.1f} dB  SSIM "
                      f"{rows[s][-1][1]:.3f}  {sec:5.2f} s")
            crops.append(row_crops)
    print(f"\nmean over {args.scenes} cell scenes, 640x480, reference {args.ref_spp} spp depth 6 "
          "(ratio: seconds / the reference's)\n")
    print("| setting | PSNR dB | SSIM | s/image | time ratio vs reference | dB vs demo's old |")
    print("|---|---|---|---|---|---|")
    base = np.mean([r[0] for r in rows[BASELINE]])
    for s in SETTINGS:
        m = np.mean(np.array(rows[s]), axis=0)
        print(f"| {label(s)} | {m[0]:.1f} | {m[1]:.3f} | {m[2]:.2f} | {m[3]:.3f} | "
              f"{m[0] - base:+.1f} |")
    if args.save is not None:  # a 160x120 crop of the image centre per setting, one row per scene
        tiles = [np.concatenate([c[180:300, 240:400] for c in row], axis=1) for row in crops]
        cv2.imwrite(str(args.save), cv2.cvtColor(np.concatenate(tiles), cv2.COLOR_RGB2BGR))
        print(f"crops (reference first, then the settings in order): {args.save}")


if __name__ == "__main__":
    main()
