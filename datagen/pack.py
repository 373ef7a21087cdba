"""Pack BOP scenes into ArrayRecord shards of training examples: ``python -m datagen.pack``.

::

    python -m datagen.pack --scenes SPLIT_DIR [SPLIT_DIR ...] --out OUT [--name train] \\
        [--num-shards N] [--split-label train|val] [--bank-size 96] [--num-templates 5140]

``--scenes`` takes BOP split folders (folders of ``{scene_id:06d}/`` scenes): the generator's
``OUT/train_pbr``, several shards' ``data/shard-*/train_pbr``, or a published BOP training set
such as ``tless/train_pbr`` (BOP's PBR training images are in exactly this format). Each
folder's models are read from ``../models`` (or ``--models``). The output::

    OUT/{name}/shard-00000-of-0000N.array_record   one record per image (per view)
    OUT/{name}/index.json                          sources, record counts per shard
    OUT/objects.json                               the object table (threept_jax.data.banks)
    OUT/models/obj_XXXXXX.ply                      the models, renumbered to the table's ids
    OUT/banks/obj_XXXXXX.npz                       render banks (datagen.banks)

A record is ``threept_jax.data.records.encode_example`` of one image: the RGB image, K,
``T_cam_world`` (identity when the dataset has no extrinsics), and per instance the object id
(a key of ``objects.json``), ``T_cam_obj``, the amodal and visible boxes (xyxy: BOP's
``[x, y, w, h]`` as ``[x, y, x + w, y + h]``; ``[-1, -1, -1, -1]`` when nothing is visible),
``visib_fract`` and the visible mask (one 16-bit instance map; should visible masks of a real
dataset overlap, the pixel goes to the lower GT index). Every GT instance is kept, invisible
ones included: the training pipeline filters. Records are ordered by source, scene and image
and split into contiguous shards; read them with ``grain.sources.ArrayRecordDataSource`` and
``records.decode_example``.

**Object ids.** Objects are identified by the SHA-256 of their model file (and texture): the
same mesh from several sources or shards gets one id. A source's own id is kept when it is free
in the table, otherwise the next free id is used. Calling the packer again on the same ``OUT``
(e.g. ``--name val --split-label val``) extends ``objects.json``.
"""

from __future__ import annotations

import argparse
import collections
import concurrent.futures
import dataclasses
import hashlib
import itertools
import json
import multiprocessing
import pathlib
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np

# Only light imports at module level: encoding workers are spawned processes that import this
# module, and need neither JAX nor Mitsuba (datagen.scene and datagen.banks are imported where
# used).
from threept_jax.data import bop, records
from threept_jax.data.banks import BANK_SIZE, BANK_TEMPLATES
from threept_jax.data.files import atomic_path, atomic_write_json

SHARD_PATTERN = "shard-{:05d}-of-{:05d}.array_record"
TABLE = "objects.json"
#: Smallest bank render side, pixels (as ``python -m datagen.banks --size``).
MIN_BANK_SIZE = 8
#: Fewest faces a closed mesh has (a tetrahedron): the smallest decimation budget for banks.
MIN_BANK_FACES = 4


class PackError(ValueError):
    """A source cannot be packed, or an option is out of range (the message names the fix).

    The command line prints it as ``error: ...`` and exits with status 2.
    """


# --------------------------------------------------------------------------------------------
# Sources and objects.


@dataclasses.dataclass(frozen=True)
class Source:
    """One BOP split folder to pack, with its models folder and object names."""

    split_dir: pathlib.Path
    models_dir: pathlib.Path
    sensor: str | None
    name: str
    object_names: dict[int, str]

    @property
    def label(self) -> str:
        """``dataset/split`` (e.g. ``tless/train_pbr``), the records' ``source`` field."""
        return f"{self.split_dir.parent.name}/{self.split_dir.name}"


def _object_names(split_dir: pathlib.Path, dataset: str) -> dict[int, str]:
    """Object names from the generator's manifest, else its scene logs (empty for BOP sets)."""
    names: dict[int, str] = {}
    manifest = split_dir / "manifest.json"
    if manifest.is_file():
        names.update({int(k): v for k, v in json.loads(manifest.read_text()).get(
            "objects", {}).items()})
    for info in sorted(split_dir.glob("*/datagen_info.json")):
        names.update({int(k): v for k, v in json.loads(info.read_text())["objects"].items()})
    return names


def open_source(path: str, models: str | None, sensor: str | None) -> Source:
    """Check a ``--scenes`` folder and find its models (``../models`` unless given)."""
    split_dir = pathlib.Path(path)
    if not split_dir.is_dir():
        raise PackError(f"--scenes {path} does not exist")
    if (split_dir / "models").is_dir() and not any(
        p.is_dir() and p.name.isdigit() for p in split_dir.iterdir()
    ):
        splits = sorted(p.name for p in split_dir.iterdir() if p.is_dir() and p.name != "models")
        raise PackError(
            f"--scenes {path} is a dataset root; pass one of its split folders, e.g. "
            f"{split_dir / (splits[0] if splits else 'train_pbr')}"
        )
    models_dir = pathlib.Path(models) if models else split_dir.parent / "models"
    if not (models_dir / "models_info.json").is_file():
        raise PackError(
            f"{models_dir} has no models_info.json; pass the models folder with --models"
        )
    if not bop.BopSplit(split_dir, sensor).scene_ids:
        raise PackError(f"--scenes {path} holds no scene folders ({{scene_id:06d}}/)")
    return Source(split_dir, models_dir, sensor, split_dir.parent.name,
                  _object_names(split_dir, split_dir.parent.name))


def _texture_of(ply: pathlib.Path) -> pathlib.Path | None:
    from datagen.scene import _ply_header

    lines, _ = _ply_header(ply)
    for line in lines:
        parts = line.split()
        if len(parts) >= 3 and parts[:2] == ["comment", "TextureFile"]:
            tex = ply.parent / parts[2]
            return tex if tex.is_file() else None
    return None


def model_digest(ply: pathlib.Path) -> str:
    """SHA-256 of a model's geometry and texture (the texture name in the header excluded)."""
    from datagen.scene import _ply_header

    h = hashlib.sha256()
    lines, stop = _ply_header(ply)
    header = "\n".join(x for x in lines if not x.startswith("comment TextureFile"))
    h.update(header.encode())
    with open(ply, "rb") as fh:
        fh.seek(stop)
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    tex = _texture_of(ply)
    if tex is not None:
        h.update(tex.read_bytes())
    return h.hexdigest()


def _read_table(out: pathlib.Path) -> dict[int, dict[str, Any]]:
    path = out / TABLE
    if not path.is_file():
        return {}
    return {int(k): v for k, v in json.loads(path.read_text()).items()}


def _write_table(out: pathlib.Path, table: dict[int, dict[str, Any]]) -> None:
    """``objects.json`` (``threept_jax.data.banks.load_object_table`` format, plus ``mesh``,
    ``mesh_sha256``, ``source`` and ``source_obj_id``), keys in numeric order."""
    rows = {str(k): table[k] for k in sorted(table)}
    atomic_write_json(out / TABLE, rows, indent=1, sort_keys=True)


def assign_objects(
    sources: Sequence[Source],
    used: Sequence[set[int]],
    out: pathlib.Path,
    split_label: str | None,
) -> tuple[dict[int, dict[str, Any]], list[dict[int, int]]]:
    """Merge the sources' objects into the table of ``out``; copy their models.

    Returns (table, per-source {source obj_id: table id}). ``used[i]`` are the obj_ids that
    source i's GT refers to.
    """
    from datagen.scene import copy_bop_model

    table = _read_table(out)
    by_digest = {row.get("mesh_sha256"): oid for oid, row in table.items()}
    maps = []
    (out / "models").mkdir(parents=True, exist_ok=True)
    for src, ids in zip(sources, used):
        models = bop.load_models(src.models_dir)
        mapping = {}
        for oid in sorted(ids):
            model = models.get(oid)
            if model is None or model.path is None:
                raise PackError(
                    f"{src.split_dir}: GT refers to object {oid}, which {src.models_dir} lacks "
                    "(models_info.json entry and obj_{id:06d}.ply are both needed)"
                )
            digest = model_digest(model.path)
            if digest in by_digest:
                mapping[oid] = by_digest[digest]
                continue
            new = oid if oid not in table else max(table) + 1
            dst = out / "models" / f"obj_{new:06d}.ply"
            copy_bop_model(model.path, dst)
            row: dict[str, Any] = dict(model.to_json())
            for k in ("min_x", "min_y", "min_z", "size_x", "size_y", "size_z"):
                row.pop(k)
            row.update(
                name=src.object_names.get(oid, f"{src.name}/obj_{oid:06d}"),
                bank=f"banks/obj_{new:06d}.npz",
                mesh=f"models/obj_{new:06d}.ply",
                mesh_sha256=digest,
                source=str(src.models_dir),
                source_obj_id=oid,
            )
            if split_label is not None:
                row["split"] = split_label
            table[new] = row
            by_digest[digest] = new
            mapping[oid] = new
        maps.append(mapping)
    return table, maps


# --------------------------------------------------------------------------------------------
# Records.

_SCENES: collections.OrderedDict[tuple, bop.BopScene] = collections.OrderedDict()


def _scene(split_dir: str, sensor: str | None, scene_id: int) -> bop.BopScene:
    """A per-process cache of open scenes (their JSON is parsed once)."""
    key = (split_dir, sensor, scene_id)
    if key not in _SCENES:
        _SCENES[key] = bop.BopSplit(split_dir, sensor).scene(scene_id)
        while len(_SCENES) > 2:
            _SCENES.popitem(last=False)
    return _SCENES[key]


def _xyxy(b: Sequence[int]) -> list[float]:
    x, y, w, h = (float(v) for v in b)
    return [-1.0, -1.0, -1.0, -1.0] if w < 0 or h < 0 else [x, y, x + w, y + h]


def image_example(scene: bop.BopScene, im_id: int, obj_map: dict[int, int], source: str
                  ) -> dict[str, Any]:
    """The training example (``threept_jax.data.records``) of one BOP image."""
    rgb = scene.image(im_id)
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[..., None], 3, -1)
    if rgb.dtype != np.uint8:  # 16-bit images of some real datasets
        rgb = np.clip(rgb / 257.0, 0, 255).astype(np.uint8)
    cam = scene.cameras[im_id]
    gts = scene.gt.get(im_id, [])
    if gts and im_id not in scene.gt_info:
        raise PackError(
            f"{scene.path}: image {im_id} has no scene_gt_info entry; compute it with the BOP "
            "toolkit's scripts/calc_gt_info.py"
        )
    infos = scene.gt_info.get(im_id, [])
    inst = np.zeros(rgb.shape[:2], np.uint16)
    for k, info in enumerate(infos):
        if info.px_count_visib <= 0:
            continue
        try:
            m = scene.mask_visib(im_id, k)
        except FileNotFoundError as e:
            raise PackError(
                f"{scene.path}: {e}; packing needs mask_visib/ (the BOP toolkit's "
                "scripts/calc_gt_masks.py writes it)"
            ) from None
        inst[m & (inst == 0)] = k + 1
    m = len(gts)
    return {
        "rgb": np.ascontiguousarray(rgb[..., :3]),
        "instances": inst,
        "K": cam.K.astype(np.float32),
        "T_cam_world": (np.eye(4) if cam.T_cam_world is None else cam.T_cam_world).astype(
            np.float32),
        "obj_id": np.array([obj_map[g.obj_id] for g in gts], np.int32),
        "T_cam_obj": np.array([g.T_cam_obj for g in gts], np.float32).reshape(m, 4, 4),
        "bbox_obj": np.array([_xyxy(i.bbox_obj) for i in infos], np.float32).reshape(m, 4),
        "bbox_visib": np.array([_xyxy(i.bbox_visib) for i in infos], np.float32).reshape(m, 4),
        "visib_fract": np.array([i.visib_fract for i in infos], np.float32).reshape(m),
        "scene_id": np.int32(scene.scene_id),
        "im_id": np.int32(im_id),
        "source": source,
    }


def _encode_task(task) -> list[bytes]:
    split_dir, sensor, scene_id, im_ids, obj_map, source, fmt = task
    sc = _scene(split_dir, sensor, scene_id)
    return [records.encode_example(image_example(sc, i, obj_map, source), fmt) for i in im_ids]


def _tasks(sources: Sequence[Source], maps, fmt: str, per_task: int = 16):
    """(source, scene, image-block) work items in record order."""
    for src, mapping in zip(sources, maps):
        split = bop.BopSplit(src.split_dir, src.sensor)
        for sid in split.scene_ids:
            ims = split.scene(sid).image_ids
            for i in range(0, len(ims), per_task):
                yield (str(src.split_dir), src.sensor, sid, ims[i : i + per_task], mapping,
                       src.label, fmt)


def _carry_cell(sources, out: pathlib.Path) -> None:
    """Copy the robot cell of cell datasets (``cell.json``, with the depth range detection
    assumes) into the records folder, where training's evaluation reads it; records of two
    different cells are refused."""
    cells = [c for c in (bop.load_cell(s.split_dir.parent) for s in sources) if c is not None]
    old = bop.load_cell(out)
    distinct = {json.dumps(c, sort_keys=True) for c in cells + ([old] if old and cells else [])}
    if len(distinct) > 1:
        raise PackError(f"the scenes (and {out / bop.CELL_FILE}, if any) come from different "
                        "robot cells (datagen --layout cell with other --seed or --meshes): pack "
                        "each cell into its own --out")
    if cells and old is None:
        bop.write_cell(out, cells[0])


def pack(
    scenes: Sequence[str],
    out: pathlib.Path,
    name: str = "train",
    num_shards: int = 1,
    *,
    models: str | None = None,
    sensor: str | None = None,
    split_label: str | None = None,
    image_format: str = "png",
    workers: int = 1,
    banks: bool = True,
    bank_size: int = BANK_SIZE,
    num_templates: int = BANK_TEMPLATES,
    bank_max_faces: int | None = 20000,
    bank_backend: str = "jax",
    quiet: bool = False,
) -> dict[str, Any]:
    """Pack ``scenes`` (BOP split folders) into ``out/name``; returns the index (module doc)."""
    rules = [
        (num_shards >= 1, f"--num-shards must be >= 1, got {num_shards}"),
        (workers >= 1, f"--workers must be >= 1, got {workers}"),
        (bank_size >= MIN_BANK_SIZE, f"--bank-size must be >= {MIN_BANK_SIZE}, got {bank_size}"),
        (num_templates >= 1, f"--num-templates must be >= 1, got {num_templates}"),
        (bank_max_faces is None or bank_max_faces >= MIN_BANK_FACES,
         f"--bank-max-faces must be >= {MIN_BANK_FACES}, got {bank_max_faces}"),
        (image_format in ("png", "jpg"),
         f"--image-format must be png or jpg, got {image_format!r}"),
    ]
    for ok, message in rules:
        if not ok:
            raise PackError(message)
    from array_record.python.array_record_module import ArrayRecordWriter
    from tqdm import tqdm

    out = pathlib.Path(out)
    sources = [open_source(s, models, sensor) for s in scenes]
    used, counts = [], []
    for src in sources:
        split = bop.BopSplit(src.split_dir, src.sensor)
        ids: set[int] = set()
        n = 0
        for sid in split.scene_ids:
            sc = split.scene(sid)
            n += len(sc.image_ids)
            for gts in sc.gt.values():
                ids.update(g.obj_id for g in gts)
        used.append(ids)
        counts.append(n)
    total = sum(counts)
    if total == 0:
        raise PackError(f"no images in {list(scenes)}")
    _carry_cell(sources, out)
    table, maps = assign_objects(sources, used, out, split_label)
    _write_table(out, table)

    folder = out / name
    folder.mkdir(parents=True, exist_ok=True)
    bounds = [k * total // num_shards for k in range(num_shards + 1)]
    paths = [folder / SHARD_PATTERN.format(k, num_shards) for k in range(num_shards)]
    keep = {p.name for p in paths}
    for old in folder.glob("shard-*-of-*.array_record"):
        if old.name not in keep:  # shards of an earlier packing with another shard count
            old.unlink()
    sizes = [0] * num_shards
    # Spawned, not forked: the parent may hold JAX / Mitsuba threads.
    pool = (concurrent.futures.ProcessPoolExecutor(
        workers, mp_context=multiprocessing.get_context("spawn")) if workers > 1 else None)
    try:
        results = (pool.map(_encode_task, _tasks(sources, maps, image_format), chunksize=1)
                   if pool else map(_encode_task, _tasks(sources, maps, image_format)))
        stream = (rec for block in results for rec in block)
        with tqdm(total=total, unit="img", desc=f"pack {name}", disable=quiet,
                  dynamic_ncols=True) as bar:
            for shard, path in enumerate(paths):  # fewer images than shards: empty shards
                with atomic_path(path) as tmp:
                    writer = ArrayRecordWriter(str(tmp), "group_size:1")
                    try:
                        for rec in itertools.islice(stream, bounds[shard + 1] - bounds[shard]):
                            writer.write(rec)
                            sizes[shard] += 1
                            bar.update(1)
                    finally:
                        writer.close()
    finally:
        if pool is not None:
            pool.shutdown()
    index = {
        "format_version": records.FORMAT_VERSION,
        "num_records": total,
        "shards": {p.name: n for p, n in zip(paths, sizes)},
        "sources": [{"scenes": str(s.split_dir), "models": str(s.models_dir), "images": n,
                     "obj_ids": {str(k): v for k, v in sorted(m.items())}}
                    for s, n, m in zip(sources, counts, maps)],
        "image_format": image_format,
    }
    atomic_write_json(folder / "index.json", index, indent=1, sort_keys=True)
    if banks:
        from datagen import banks as DB

        ids = sorted({v for m in maps for v in m.values()})
        DB.build_banks(out, ids, bank_size, num_templates, max_faces=bank_max_faces,
                       backend=bank_backend, quiet=quiet)
    return index


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m datagen.pack",
        description="Pack BOP scenes into ArrayRecord training shards (see the module docstring).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--scenes", nargs="+", required=True, help="BOP split folders")
    p.add_argument("--out", required=True, help="records folder (objects.json, banks/, NAME/)")
    p.add_argument("--name", default="train", help="subfolder of the shards")
    p.add_argument("--num-shards", type=int, default=1)
    p.add_argument("--models", default=None, help="models folder (default: SCENES/../models)")
    p.add_argument("--sensor", default=None, help="sensor of a multi-sensor BOP dataset")
    p.add_argument("--split-label", choices=("train", "val"), default=None,
                   help="'split' of new objects in objects.json")
    p.add_argument("--image-format", choices=("png", "jpg"), default="png",
                   help="image encoding inside the records")
    p.add_argument("--workers", type=int, default=1, help="encoding processes")
    p.add_argument("--no-banks", action="store_true", help="skip rendering the banks")
    p.add_argument("--bank-size", type=int, default=BANK_SIZE,
                   help="bank render side: the detector's render_size (tiny 32, small 112, "
                        "paper 224)")
    p.add_argument("--num-templates", type=int, default=BANK_TEMPLATES)
    p.add_argument("--bank-max-faces", type=int, default=20000)
    p.add_argument("--bank-backend", choices=("jax", "mitsuba"), default="jax")
    p.add_argument("--quiet", action="store_true")
    return p


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    from datagen import banks as DB

    args = build_parser().parse_args(argv)
    try:
        index = pack(args.scenes, pathlib.Path(args.out), args.name, args.num_shards,
                     models=args.models, sensor=args.sensor, split_label=args.split_label,
                     image_format=args.image_format, workers=args.workers,
                     banks=not args.no_banks, bank_size=args.bank_size,
                     num_templates=args.num_templates, bank_max_faces=args.bank_max_faces,
                     bank_backend=args.bank_backend, quiet=args.quiet)
    except (PackError, DB.TableError) as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    if not args.quiet:
        print(f"packed {index['num_records']} images into {len(index['shards'])} shards "
              f"in {pathlib.Path(args.out) / args.name}")
    return index


if __name__ == "__main__":
    main()
