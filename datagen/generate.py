"""Generate synthetic BOP scenes: ``python -m datagen.generate``.

::

    python -m datagen.generate --meshes DIR [DIR ...] [procedural:N] --out DIR \\
        --num-scenes N --images-per-scene M --views V --resolution W H --spp S \\
        --seed S --shard I --num-shards N [--layout drop|float|pack|mixed] \\
        [--split train|val --val-fraction F]

Output (one BOP dataset per ``--out``; see ``datagen/scene.py`` for what a scene holds)::

    OUT/models/obj_XXXXXX.ply (+ textures), models_info.json   the meshes the scenes use
    OUT/{split}_pbr/{scene_id:06d}/                              BOP scenes (+ datagen_info.json)
    OUT/{split}_pbr/manifest.json                                generator version, config, seed,
                                                                 shard, counts, skipped meshes
    OUT/test_targets_multiview_bop25.json                        multi-view runs (--views V > 1):
                                                                 one group per capture
    OUT/cell.json                                                --layout cell: the cell's camera,
                                                                 working distance, depth range

**Multi-view targets.** A run with ``--views V`` > 1 writes ``test_targets_multiview_bop25.json``
at the dataset root: one group ``{"scene_id", "im_ids": [m*V, ..., m*V + V - 1]}`` per capture
``m`` of every complete scene (``threept_jax.data.bop.load_multiview_targets`` reads it;
``python -m infer bop --targets multiview`` runs it). It is rewritten at the end of every run
from the scenes on disk, so a resumed run lists them all. The root holds one such file: when
both splits of an ``--out`` are multi-view, it lists the ``val`` split's captures (the
held-out split one evaluates on). Shards list their own scenes; merged shards concatenate
their lists (scene ids are disjoint).

**Sharding.** ``--num-scenes`` is the total over all shards; shard ``I`` of ``N`` makes the
contiguous block of scene ids ``[I * S // N, (I + 1) * S // N)``. Scene ``s`` is drawn from
``np.random.SeedSequence([seed, split, s])``, so a scene does not depend on how the work is
split, and the mesh pool (procedural parts included) and its ``obj_id``s depend only on the seed
and ``--meshes``: shards of one dataset can be merged. Give every shard its own ``--out``
(``OUT/shard-$I``): a folder that holds another shard's manifest is refused.

**Resume.** A scene is written to ``{id}.tmp/`` and renamed to ``{id}/`` when complete; a rerun
with the same arguments skips complete scenes and redoes a partial one. Every file is written
atomically (temporary file and rename), and the output is byte-identical to an uninterrupted run
(the manifest has no timestamps).

**One writer per shard.** A run holds an exclusive lock (``fcntl.flock``) on
``OUT/{split}_pbr/.datagen.lock`` while it writes; a second run of the same shard is refused
with the holder's process id. The lock dies with its process (no stale locks), and a run that
takes it first deletes the temporary folders and files (``*.tmp``) a killed run left behind.

**Held-out meshes.** ``--val-fraction F`` assigns each mesh to ``val`` when a hash of its pool
name falls below F (stable when meshes are added), and ``--split`` picks which meshes the run
may use: run once with ``--split train`` and once with ``--split val`` into one ``--out``, with
the same ``--seed``, ``--meshes`` and ``--val-fraction``: a split whose sibling's manifest says
otherwise (or holds out another mesh set) is refused, as held-out meshes would leak into
training. With ``--val-fraction 0`` every mesh is allowed, and held-out sets come from separate
``--meshes`` instead.

Bad arguments and output folders that cannot take the run are reported as ``error: ...`` (exit
status 2) before any slow work.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import errno
import fcntl
import hashlib
import json
import logging
import os
import pathlib
import socket
import sys
import warnings
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np

from datagen import cell as C
from datagen import meshes as M
from datagen import procedural as P
from datagen import scene as S
from datagen.cell import Cell
from threept_jax.data import bop
from threept_jax.data.files import atomic_write_json
from threept_jax.geometry.symmetry import Symmetries

GENERATOR = "threept_jax.datagen"
GENERATOR_VERSION = "1.0"
SPLITS = ("train", "val")
# Stream tags of the seed sequences (arbitrary distinct constants).
_PROCEDURAL_STREAM = 0x5052_4F43
_CELL_STREAM = 0x4345_4C4C
_SPLIT_STREAM = {"train": 0x5452_4149, "val": 0x5641_4C20}
INFO_FILE = "datagen_info.json"
LOCK_FILE = ".datagen.lock"


class GenerateError(ValueError):
    """Bad arguments, or an output folder that cannot take this run (the message names the fix).

    The command line prints it as ``error: ...`` and exits with status 2.
    """


# --------------------------------------------------------------------------------------------
# Mesh pool and split.


def parse_mesh_args(entries: Sequence[str]) -> tuple[list[str], int]:
    """(folders, number of procedural parts) from ``--meshes`` entries (``procedural:N``)."""
    folders, n_proc = [], 0
    for e in entries:
        if e.startswith("procedural:"):
            try:
                n = int(e.split(":", 1)[1])
            except ValueError:
                raise ValueError(
                    f"--meshes entry {e!r}: write procedural:N with an integer N, e.g. "
                    "procedural:200"
                ) from None
            if n < 1:
                raise ValueError(f"--meshes entry {e!r}: N must be >= 1")
            n_proc += n
        else:
            if not pathlib.Path(e).is_dir():
                raise ValueError(
                    f"--meshes entry {e!r} is neither a folder nor procedural:N; pass BOP "
                    "models folders, trees of mesh files, or procedural:N"
                )
            folders.append(e)
    return folders, n_proc


def build_pool(
    entries: Sequence[str], seed: int, units: str = "mm", procedural_max_faces: int = 5000
) -> M.MeshPool:
    """The mesh pool of a run: folders in order, then the procedural parts of ``seed``.

    Depends only on the mesh arguments and the seed (never on the shard), so obj_ids agree
    across shards and splits.
    """
    folders, n_proc = parse_mesh_args(entries)
    parts: list[P.Part] = []
    if n_proc:
        rng = np.random.default_rng(np.random.SeedSequence([seed, _PROCEDURAL_STREAM]))
        parts = P.generate_parts(rng, n_proc, max_faces=procedural_max_faces)
    # A mesh in the wrong units is skipped with a message that names this CLI's flag.
    return M.build_pool([M.MeshFolder(f, units=units) for f in folders], parts,
                        units_option="--mesh-units {}")


def mesh_split(name: str, val_fraction: float) -> str:
    """'val' or 'train' for a pool mesh name: a hash of the name against ``val_fraction``."""
    h = int.from_bytes(hashlib.sha256(name.encode()).digest()[:8], "big") / 2.0**64
    return "val" if h < val_fraction else "train"


def design_cell(pool: M.MeshPool, seed: int, resolution: tuple[int, int],
                views: int = 1) -> Cell:
    """The robot cell of a ``--layout cell`` dataset, seen by ``views`` cameras: drawn from the
    seed and the diameters of every usable mesh of the pool, so every split and shard of the
    dataset shares it."""
    diameters = [m.diameter for m in map(pool.load, range(len(pool))) if m is not None]
    if not diameters:
        raise ValueError("no usable mesh in --meshes: a cell needs its parts' diameters")
    rng = np.random.default_rng(np.random.SeedSequence([seed, _CELL_STREAM]))
    return C.design_cell(rng, diameters, resolution, views)


def split_candidates(pool: M.MeshPool, split: str, val_fraction: float) -> list[int]:
    """Pool indices the split may use (all of them when ``val_fraction`` is 0)."""
    if val_fraction <= 0:
        return list(range(len(pool)))
    return [i for i, r in enumerate(pool.records) if mesh_split(r.name, val_fraction) == split]


def pool_fingerprint(pool: M.MeshPool) -> str:
    h = hashlib.sha256()
    for r in pool.records:
        h.update(f"{r.obj_id} {r.name}\n".encode())
    return h.hexdigest()[:16]


def held_out(pool: M.MeshPool, val_fraction: float) -> dict[str, Any]:
    """The meshes held out for ``val`` (none when ``val_fraction`` is 0): count and fingerprint,
    as the manifest's ``held_out`` records them."""
    names = sorted(r.name for r in pool.records
                   if val_fraction > 0 and mesh_split(r.name, val_fraction) == "val")
    digest = hashlib.sha256("".join(f"{n}\n" for n in names).encode()).hexdigest()[:16]
    return {"num_meshes": len(names), "fingerprint": digest}


def shard_scene_ids(num_scenes: int, shard: int, num_shards: int) -> range:
    """Scene ids of one shard: a contiguous block, sizes differing by at most one."""
    return range(shard * num_scenes // num_shards, (shard + 1) * num_scenes // num_shards)


def scene_rng(seed: int, split: str, scene_id: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([seed, _SPLIT_STREAM[split], scene_id]))


# --------------------------------------------------------------------------------------------
# Models and manifest.


def update_models_info(models_dir: pathlib.Path, pool: M.MeshPool) -> int:
    """Add ``models_info.json`` entries for every ``obj_*.ply`` in ``models_dir`` lacking one.

    Entries are computed from the written PLY (exact diameter and box, as the BOP toolkit's
    ``calc_model_info.py``) with the pool's symmetries, so they depend only on the files.
    Returns the number of entries.
    """
    path = models_dir / "models_info.json"
    existing = bop.load_models_info(path) if path.is_file() else {}
    by_id = {r.obj_id: r for r in pool.records}
    changed = False
    for ply in sorted(models_dir.glob("obj_*.ply")):
        oid = int(ply.stem.split("_")[1])
        if oid in existing:
            continue
        rec = by_id.get(oid)
        sym = rec.symmetries if rec is not None else Symmetries()
        from threept_jax.data.ply import load_ply_vertices

        existing[oid] = bop.compute_model_info(load_ply_vertices(ply), sym, oid, ply)
        changed = True
    if changed or not path.is_file():
        bop.write_models_info(path, dict(sorted(existing.items())))
    return len(existing)


def _manifest_identity(m: dict[str, Any]) -> dict[str, Any]:
    keys = ("generator", "version", "seed", "shard", "num_shards", "split", "config", "pool")
    out = {k: m.get(k) for k in keys}
    cell = (out["config"] or {}).get("cell")
    if cell is not None and "views" not in cell:  # written before cells had rigs: one camera
        out["config"] = {**out["config"], "cell": {**cell, "views": 1}}
    return out


def check_siblings(out: pathlib.Path, manifest: dict[str, Any]) -> None:
    """Refuse a split whose sibling splits in ``out`` (their manifests) were generated from
    another seed, mesh pool or units, or hold out other meshes: the splits share ``models/``,
    and a mesh held out from training must stay out of it, whichever split came first."""
    mine = manifest["config"]
    for other in sorted(out.glob("*_pbr/manifest.json")):
        o = json.loads(other.read_text())
        if o.get("split") == manifest["split"]:
            continue  # this split's own manifest: check_output
        theirs = o.get("config", {})
        # (flag, this run's value, the sibling's, whether they differ)
        rows = [(flag, mine_v, their_v, mine_v != their_v) for flag, mine_v, their_v in (
            ("--seed", manifest["seed"], o.get("seed")),
            ("--val-fraction", mine["val_fraction"], theirs.get("val_fraction")),
            ("--mesh-units", mine["mesh_units"], theirs.get("mesh_units")),
            ("--procedural-max-faces", mine["procedural_max_faces"],
             theirs.get("procedural_max_faces")),
        )]
        # Equal pools may be named by other paths: the pool's fingerprint decides.
        rows.append(("--meshes", " ".join(mine["meshes"]), " ".join(theirs.get("meshes", [])),
                     o.get("pool", {}).get("fingerprint") != manifest["pool"]["fingerprint"]))
        for flag, value, seen, differ in rows:
            if differ:
                raise GenerateError(
                    f"{flag} {value} differs from {flag} {seen} of the {o.get('split')} split "
                    f"in this --out ({other}); the splits of one --out share models/ and must "
                    "hold out the same meshes, or held-out meshes leak into training: rerun "
                    f"with {flag} {seen}, or choose a new --out"
                )
        if "held_out" in o and o["held_out"] != manifest["held_out"]:
            raise GenerateError(
                f"{other} holds out {o['held_out']['num_meshes']} meshes (fingerprint "
                f"{o['held_out']['fingerprint']}), this run would hold out "
                f"{manifest['held_out']['num_meshes']} ({manifest['held_out']['fingerprint']}) "
                "from the same arguments (another generator version?); regenerate both splits "
                "into a new --out"
            )


def check_output(split_dir: pathlib.Path, manifest: dict[str, Any]) -> None:
    """Refuse a split folder that holds another configuration or another shard."""
    mpath = split_dir / "manifest.json"
    if not mpath.is_file():
        return
    out = split_dir.parent
    old = json.loads(mpath.read_text())
    if (old.get("shard"), old.get("num_shards")) != (manifest["shard"], manifest["num_shards"]):
        raise GenerateError(
            f"{out} already holds shard {old.get('shard')} of {old.get('num_shards')}; "
            f"every shard needs its own --out (e.g. --out {out.parent}/shard-$I)"
        )
    if _manifest_identity(old) != _manifest_identity(manifest):
        diff = [k for k, v in _manifest_identity(manifest).items() if old.get(k) != v]
        raise GenerateError(
            f"{mpath} was written with different arguments ({', '.join(diff)} differ); "
            "rerun with the same arguments to resume, or choose a new --out"
        )


@contextlib.contextmanager
def shard_lock(split_dir: pathlib.Path, shard: int, num_shards: int) -> Iterator[None]:
    """Hold the exclusive writer lock of ``split_dir`` (``LOCK_FILE``, ``fcntl.flock``).

    Raises GenerateError naming the holder when another process holds it. While held, the file
    names this process; it is emptied on release, so finished outputs stay byte-identical. The
    kernel drops the lock when its process dies: a lock is never stale.
    """
    split_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(split_dir / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                holder = json.loads(os.pread(fd, 4096, 0))
            except ValueError:  # taken a moment ago, not yet signed
                holder = {}
            pid = holder.get("pid", "?")
            raise GenerateError(
                f"shard {holder.get('shard', '?')} of {holder.get('num_shards', '?')} in "
                f"{split_dir} is being written by process {pid} on host "
                f"{holder.get('host', '?')}; wait for it to finish, or stop it (kill {pid}) "
                "and rerun the same command to resume"
            ) from None
        except OSError as e:
            if e.errno not in (errno.ENOLCK, errno.ENOSYS, errno.EOPNOTSUPP):
                raise
            warnings.warn(f"{split_dir} does not support file locks ({e}); make sure no other "
                          "run writes this shard", stacklevel=3)
        sign = {"pid": os.getpid(), "host": socket.gethostname(), "shard": shard,
                "num_shards": num_shards}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(sign).encode(), 0)
        try:
            yield
        finally:
            os.ftruncate(fd, 0)
    finally:
        os.close(fd)  # releases the lock


def remove_stale_temporaries(split_dir: pathlib.Path) -> list[str]:
    """Delete the ``*.tmp`` folders (partial scenes) and files (atomic writes) a killed run left
    in ``split_dir``; call with the shard lock held. Returns their names."""
    stale = sorted(p for p in split_dir.iterdir() if p.name.endswith(".tmp"))
    for p in stale:
        if p.is_dir() and not p.is_symlink():
            S.remove_tree(p)
        else:
            p.unlink()
    return [p.name for p in stale]


def check_args(args: argparse.Namespace) -> None:
    """Refuse out-of-range numeric options, naming the flag, before any slow work."""
    (w, h), (dlo, dhi), (xlo, xhi) = args.resolution, args.distinct, args.distractors
    rules = [
        (args.num_scenes >= 1, f"--num-scenes must be >= 1, got {args.num_scenes}"),
        (args.images_per_scene >= 1,
         f"--images-per-scene must be >= 1, got {args.images_per_scene}"),
        (args.views >= 1, f"--views must be >= 1, got {args.views}"),
        (min(w, h) >= S.MIN_SIDE,
         f"--resolution W H must be at least {S.MIN_SIDE} {S.MIN_SIDE}, got {w} {h}"),
        (args.spp >= 1, f"--spp must be >= 1, got {args.spp}"),
        (args.seed >= 0, f"--seed must be >= 0 (NumPy seed sequences take non-negative "
                         f"integers), got {args.seed}"),
        (args.num_shards >= 1, f"--num-shards must be >= 1, got {args.num_shards}"),
        (0 <= args.shard < args.num_shards,
         f"--shard must lie in [0, --num-shards), got {args.shard} of {args.num_shards}"),
        (0.0 <= args.val_fraction < 1.0,
         f"--val-fraction must lie in [0, 1), got {args.val_fraction}"),
        (args.instances >= 1, f"--instances must be >= 1, got {args.instances}"),
        (1 <= dlo <= dhi, f"--distinct MIN MAX needs 1 <= MIN <= MAX, got {dlo} {dhi}"),
        (0 <= xlo <= xhi, f"--distractors MIN MAX needs 0 <= MIN <= MAX, got {xlo} {xhi}"),
        (0.0 <= args.closeup_probability <= 1.0,
         f"--closeup-probability must lie in [0, 1], got {args.closeup_probability}"),
        (args.max_depth == -1 or args.max_depth >= S.MIN_MAX_DEPTH,
         f"--max-depth must be -1 (unbounded) or >= {S.MIN_MAX_DEPTH}, got {args.max_depth}: "
         "Mitsuba's path tracer renders nothing at 0 and only the light sources at 1 (black "
         "objects)"),
        (args.procedural_max_faces >= P.MIN_MAX_FACES,
         f"--procedural-max-faces must be >= {P.MIN_MAX_FACES} (the simplest part families "
         f"need them), got {args.procedural_max_faces}"),
        (args.threads >= 0, f"--threads must be >= 0 (0: all cores), got {args.threads}"),
    ]
    for ok, message in rules:
        if not ok:
            raise GenerateError(message)


# --------------------------------------------------------------------------------------------
# The run.


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Generate this shard's scenes (resuming); returns the final manifest.

    Raises GenerateError (before any slow work where it can) for bad arguments and output
    folders that cannot take the run.
    """
    check_args(args)
    try:  # configuration errors: one clear line, no traceback
        pool = build_pool(args.meshes, args.seed, args.mesh_units, args.procedural_max_faces)
        cell = design_cell(pool, args.seed, tuple(args.resolution), args.views) \
            if args.layout == "cell" else None
        cfg = S.SceneConfig(
            resolution=(args.resolution[0], args.resolution[1]),
            spp=args.spp,
            views=args.views,
            images_per_scene=args.images_per_scene,
            layout=args.layout,
            instances=args.instances,
            distinct=tuple(args.distinct),
            distractors=tuple(args.distractors),
            image_format=args.image_format,
            max_depth=args.max_depth,
            denoise=args.denoise,
            closeup_probability=args.closeup_probability,
            cell=cell,
        )
    except ValueError as e:
        raise GenerateError(str(e)) from e
    out = pathlib.Path(args.out)
    split_dir = out / f"{args.split}_pbr"
    candidates = split_candidates(pool, args.split, args.val_fraction)
    scene_ids = shard_scene_ids(args.num_scenes, args.shard, args.num_shards)
    config = {k: v for k, v in dataclasses.asdict(cfg).items()}
    config.update(meshes=list(args.meshes), mesh_units=args.mesh_units,
                  num_scenes=args.num_scenes, val_fraction=args.val_fraction,
                  procedural_max_faces=args.procedural_max_faces)
    config = json.loads(json.dumps(config))  # tuples -> lists, as read back
    manifest: dict[str, Any] = {
        "generator": GENERATOR,
        "version": GENERATOR_VERSION,
        "seed": args.seed,
        "shard": args.shard,
        "num_shards": args.num_shards,
        "split": args.split,
        "config": config,
        "pool": {"num_meshes": len(pool), "fingerprint": pool_fingerprint(pool),
                 "split_meshes": len(candidates)},
        "held_out": held_out(pool, args.val_fraction),
        "scene_ids": [scene_ids.start, scene_ids.stop],
        "status": "running",
    }
    check_siblings(out, manifest)
    if not candidates:
        raise GenerateError(
            f"no mesh of the pool ({len(pool)} meshes) falls in split {args.split!r} at "
            f"--val-fraction {args.val_fraction}; raise it or add meshes"
        )
    if args.threads > 0:
        import drjit as dr

        from threept_jax.render.mitsuba_backend import load_mitsuba

        load_mitsuba()
        dr.set_thread_count(args.threads)
    with shard_lock(split_dir, args.shard, args.num_shards):
        check_output(split_dir, manifest)
        remove_stale_temporaries(split_dir)
        return _write_shard(args, cfg, pool, candidates, split_dir, manifest)


def _write_shard(
    args: argparse.Namespace,
    cfg: S.SceneConfig,
    pool: M.MeshPool,
    candidates: list[int],
    split_dir: pathlib.Path,
    manifest: dict[str, Any],
) -> dict[str, Any]:
    """The scenes of the shard (``run`` holds its lock), then the final manifest."""
    from tqdm import tqdm

    models_dir = split_dir.parent / "models"
    scene_ids = range(*manifest["scene_ids"])
    atomic_write_json(split_dir / "manifest.json", manifest, indent=1, sort_keys=True)
    models_dir.mkdir(parents=True, exist_ok=True)
    update_models_info(models_dir, pool)
    if cfg.cell is not None:
        bop.write_cell(split_dir.parent, cfg.cell.to_json())

    assets = S.AssetCache(pool, models_dir)
    done = [s for s in scene_ids if (split_dir / f"{s:06d}" / INFO_FILE).is_file()]
    bar = tqdm(
        total=len(scene_ids) * cfg.images,
        initial=len(done) * cfg.images,
        unit="img",
        desc=f"shard {args.shard}/{args.num_shards} {args.split}",
        dynamic_ncols=True,
        disable=args.quiet,
    )
    totals = S.Timings()
    for s in scene_ids:
        final = split_dir / f"{s:06d}"
        if (final / INFO_FILE).is_file():
            continue
        tmp = split_dir / f"{s:06d}.tmp"  # partial scenes of killed runs are removed by now
        if final.exists():
            S.remove_tree(final)
        res = S.generate_scene(tmp, s, scene_rng(args.seed, args.split, s), assets, candidates,
                               cfg, on_image=lambda: bar.update(1))
        atomic_write_json(tmp / INFO_FILE, res.info, indent=1, sort_keys=True)
        os.replace(tmp, final)
        update_models_info(models_dir, pool)
        for f in dataclasses.fields(totals):
            setattr(totals, f.name, getattr(totals, f.name) + getattr(res.timings, f.name))
    bar.close()

    # The manifest summarises the completed scenes from their info files, so it is the same
    # whether the run was resumed or not.
    objects: dict[str, str] = {}
    skipped: dict[str, str] = {}
    layouts: dict[str, int] = {}
    n_inst = 0
    for s in scene_ids:
        info = json.loads((split_dir / f"{s:06d}" / INFO_FILE).read_text())
        objects.update(info["objects"])
        skipped.update(info["skipped_meshes"])
        layouts[info["layout"]] = layouts.get(info["layout"], 0) + 1
        n_inst += info["num_targets"]
    manifest.update(
        status="complete",
        num_scenes=len(scene_ids),
        num_images=len(scene_ids) * cfg.images,
        instances_per_scene=n_inst / max(len(scene_ids), 1),
        layouts=dict(sorted(layouts.items())),
        objects=dict(sorted(objects.items(), key=lambda kv: int(kv[0]))),
        skipped_meshes=len(skipped),
        skipped_mesh_reasons=dict(sorted(skipped.items())),
    )
    atomic_write_json(split_dir / "manifest.json", manifest, indent=1, sort_keys=True)
    targets = multiview_targets(split_dir.parent)
    if targets is not None:
        bop.write_multiview_targets(split_dir.parent / bop.MULTIVIEW_TARGETS_FILE, targets)
    if not args.quiet:
        t = totals
        spent = t.physics + t.compose + t.render + t.annotate + t.write
        if spent > 0:
            print(
                f"{len(scene_ids) - len(done)} scenes generated ({len(done)} already done): "
                f"physics {t.physics:.1f} s, composition {t.compose:.1f} s, "
                f"rendering {t.render:.1f} s, masks {t.annotate:.1f} s, "
                f"writing {t.write:.1f} s; "
                f"{len(skipped)} meshes skipped",
                file=sys.stderr,
            )
    return manifest


def multiview_targets(out: pathlib.Path) -> list[bop.MultiviewTarget] | None:
    """The multi-view groups of the dataset root ``out`` (module docstring): one per capture of
    every complete scene of its multi-view split (``val`` when both splits are), None when no
    split of ``out`` is multi-view."""
    multiview = [split for split in SPLITS
                 if (out / f"{split}_pbr" / "manifest.json").is_file()
                 and json.loads((out / f"{split}_pbr" / "manifest.json").read_text())
                 ["config"]["views"] > 1]
    if not multiview:
        return None
    split_dir = out / f"{'val' if 'val' in multiview else multiview[0]}_pbr"
    scenes = sorted(int(d.name) for d in split_dir.iterdir()
                    if d.name.isdigit() and (d / INFO_FILE).is_file())
    groups = []
    for s in scenes:
        info = json.loads((split_dir / f"{s:06d}" / INFO_FILE).read_text())
        V = info["views"]
        groups += [bop.MultiviewTarget(s, tuple((None, m * V + v) for v in range(V)))
                   for m in range(info["captures"])]
    return groups


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m datagen.generate",
        description="Render synthetic BOP scenes with Mitsuba (see the module docstring).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--meshes", nargs="+", required=True,
                   help="BOP models folders, trees of mesh files, and/or procedural:N")
    p.add_argument("--out", required=True, help="dataset folder (one per shard)")
    p.add_argument("--num-scenes", type=int, required=True, help="scenes over all shards")
    p.add_argument("--images-per-scene", type=int, default=1, help="captures M per scene")
    p.add_argument("--views", type=int, default=1,
                   help="cameras V per capture (if > 1: a ring rig, or with --layout cell the "
                        "cell's rig: V cameras 15 degrees off the vertical, datagen/cell.py)")
    p.add_argument("--resolution", type=int, nargs=2, default=(640, 480), metavar=("W", "H"))
    p.add_argument("--spp", type=int, default=4,
                   help="path-tracing samples per pixel (denoised unless --no-denoise)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--shard", type=int, default=0)
    p.add_argument("--num-shards", type=int, default=1)
    p.add_argument("--layout", choices=S.LAYOUTS, default="mixed",
                   help="cell: a fixed camera (or --views rig) above a tray at a working "
                        "distance, written to OUT/cell.json (datagen/cell.py); the others: "
                        "random views")
    p.add_argument("--split", choices=SPLITS, default="train")
    p.add_argument("--val-fraction", type=float, default=0.0,
                   help="share of meshes held out for --split val (0: no split)")
    p.add_argument("--instances", type=int, default=30,
                   help="mean annotated instances per scene (the paper averages ~110)")
    p.add_argument("--distinct", type=int, nargs=2, default=(1, 20), metavar=("MIN", "MAX"),
                   help="distinct meshes per scene")
    p.add_argument("--distractors", type=int, nargs=2, default=(0, 5), metavar=("MIN", "MAX"))
    p.add_argument("--closeup-probability", type=float, default=0.3,
                   help="share of single views aimed at part of the scene (truncated objects)")
    p.add_argument("--image-format", choices=("jpg", "png"), default="jpg")
    p.add_argument("--max-depth", type=int, default=6, help="path length of the path tracer")
    p.add_argument("--denoise", action=argparse.BooleanOptionalAction, default=True,
                   help="clean the path-traced images with Open Image Denoise fed the albedo and "
                        "normal of the same samples (bench/datagen_quality.py measures the gain "
                        "per second); recorded in the manifest's config")
    p.add_argument("--mesh-units", choices=sorted(M.UNITS_TO_MM), default="mm",
                   help="units of the mesh folders (BOP models are in mm)")
    p.add_argument("--procedural-max-faces", type=int, default=P.DEFAULT_MAX_FACES)
    p.add_argument("--threads", type=int, default=0,
                   help="Mitsuba (Dr.Jit) worker threads; 0: all cores. The output does not "
                   "depend on it")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    # trimesh logs a traceback for every PLY whose texture file is missing (most YCB-V models
    # in ../shared); such meshes render untextured, which is not an error here.
    logging.getLogger("trimesh").setLevel(logging.CRITICAL)
    try:
        return run(build_parser().parse_args(argv))
    except GenerateError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        main()
