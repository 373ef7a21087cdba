"""A lent GPU's minutes spent on 3PT-R, resumed across draws (issue 40; docs/training.md, "A
lent GPU").

A lent machine has its own Python, JAX, Flax, Optax, Orbax and OpenCV, no network, takes 64 MiB
of files per call and gives 15 minutes of device time per session. What it lacks travels as
wheels and the training data as a JPEG subset of a records folder (``.device/``, ignored by
git, carried); the run lives in ``models/refiner-gpu-run`` (:data:`RUN`) and travels with the
working tree, which the call limits to 64 MiB with the carry. Three steps:

    # here, before a draw: the carry
    python scripts/device.py prepare --records runs/demo/adapted/records
    # on the device (the run tool; carry .device): one command, MINUTES of wall time in all
    bash scripts/device_run.sh 11
    # here, after it: the run back in models/refiner-gpu-run (commit it to keep it)
    python scripts/device.py unpack --files FILES_AT

``run`` (what ``device_run.sh`` calls after installing the missing wheels) writes to ``$OUT``:
``env.json`` (Python, packages, devices), ``mfu.txt`` (the train-step benchmarks of 3PT-D and
3PT-R at the ``small`` and ``paper`` sizes: compile time, step time, FLOP/s, MFU against the
device's peak bf16), ``train.log``, ``run.tar.gz.NN`` (the training run folder with its last
checkpoint, in 15 MB parts) and ``summary.json`` (each training stage's steps before and after,
minutes of each stage). Training goes through two stages (:data:`STAGES`): ALIKED frozen for
:data:`FROZEN_STEPS`, then the whole network fine-tuned from that run, in the same draw when
time is left. It resumes from :data:`RUN` when it is there, in the stage that run is in;
SIGTERM at the deadline saves a checkpoint, so a draw that ends early still brings back its
last one. ``--dry-run`` runs every stage at the ``tiny`` size for a few steps: the tests run it
on CPU.
"""

from __future__ import annotations

import argparse
import functools
import importlib.metadata
import importlib.util
import io
import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import tarfile
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
# The project's packages and scripts/ (gpu_detector's subset), also when imported by the tests.
sys.path[:0] = [str(ROOT), str(ROOT / "scripts")]
#: What the training needs beyond the device's own stack: distribution -> its import name.
#: (The imports of the trainers and the benchmarks, against the device's package list: grain,
#: array-record, ml-collections, portpicker and pycocotools are not on it.)
NEEDED = {"grain": "grain", "array-record": "array_record", "ml-collections": "ml_collections",
          "trimesh": "trimesh", "cloudpickle": "cloudpickle", "portpicker": "portpicker",
          "PyYAML": "yaml", "pycocotools": "pycocotools"}
#: The device's Python (the wheels are downloaded for it).
DEVICE_PYTHON = "3.12"
#: What one call may carry: the working tree and the carry together (the run tool's limit).
CALL_LIMIT = 64 * 2**20
#: What may come back from one call: at most 8 files of 16 MiB, 64 MiB in all (the run tool's
#: limit); the run travels as up to 4 parts beside the four small files.
PART_BYTES = 15 * 2**20
RUN_LIMIT = 4 * PART_BYTES
#: The refiner trained on the device: the ``cpu`` size (mini/16, 2.3 M parameters) reading
#: ALIKED (aliked-n16, 0.68 M parameters) as its pretrained stem with ``stem_descriptors`` (the
#: descriptors start as ALIKED's features and the head learns a correction): the best matcher
#: trained on CPU, 1.8 x and 2.5 x position alone on the two held-out sets at 128 px crops
#: (docs/training.md, "Pretrained stems: ALIKED"). On the device at 256 px crops, where ALIKED's
#: own features match best (issue 40's measurement: 0.53 against position's 0.26), batch 32:
#: the memory plan (:data:`MEMORY_LIMIT`) is 35 GiB, where batch 64 would be 70 GiB, too near an
#: H100's 80. Its training state (parameters and Adam's two moments, float32, 35.6 MiB)
#: travels both ways; that of ``small`` (S/14, 35.9 M parameters: 430 MB) cannot.
CONFIG = "cpu"
CONFIG_OVERRIDES = ("--config.model.crop_size=256", "--config.model.output_size=64",
                    "--config.model.pretrained_stem=aliked",
                    "--config.model.stem_descriptors=True", "--config.model.descriptor_dim=128",
                    "--config.batch_size=32")
#: The most one training step of :data:`CONFIG` may need on the device (``memory_plan``, the
#: fine-tuning stage's, which keeps the stem's activations too): half of an H100's 80 GiB, so
#: that XLA's own buffers and the matching loss fit beside it.
MEMORY_LIMIT = 40 * 2**30
#: The plan's two stages, the recipe that worked on CPU (docs/training.md, "Pretrained stems":
#: the gain came with fine-tuning, not with more frozen steps): the stem frozen for
#: ``FROZEN_STEPS``, then the whole network fine-tuned from the frozen run's best checkpoint
#: (a new run, ``init_from``) at a lower learning rate for the rest of :data:`PLAN_STEPS`.
FROZEN_STEPS = 2000
STAGES = {"frozen": ("--config.optim.freeze=stem",),
          "fine-tune": ("--config.optim.freeze=", "--config.optim.learning_rate=3e-4")}
#: The dry run's (CPU, tests): the device's stem and stages, at the ``tiny`` size.
DRY_CONFIG = "tiny"
DRY_FROZEN_STEPS = 2
DRY_OVERRIDES = ("--config.model.pretrained_stem=aliked", "--config.model.stem_descriptors=True",
                 "--config.model.descriptor_dim=128",
                 "--config.batch_size=2", "--config.mesh.data=1",
                 "--config.data.num_hypotheses=2", "--config.refine.max_faces=256",
                 "--config.refine.num_matches=16", "--config.eval.every_steps=0",
                 "--config.checkpoint.every_steps=1", "--config.log_every=1")
#: The T-LESS models ``bench/refiner_step.py`` renders (carried: ../shared does not travel).
BENCH_MESHES = (4, 5, 6, 7)
#: Share of the call the MFU table may take (the rest trains).
MFU_SHARE = 0.3
#: Where the device's run lives between draws (it travels with the working tree).
RUN = ROOT / "models" / "refiner-gpu-run"
#: Steps of the whole plan: each stage's learning-rate schedule spans the draws it takes (each
#: resumes it).
PLAN_STEPS = 20000
#: The least time left in a draw worth starting the fine-tuning stage in (its compilation).
MIN_STAGE_SECONDS = 180


def _wheel_dist(path: pathlib.Path) -> str:
    return path.name.split("-")[0].replace("_", "-").lower()


def missing(wheels: pathlib.Path) -> list[pathlib.Path]:
    """The carried wheels of :data:`NEEDED` whose module this Python cannot import."""
    want = {d.lower(): m for d, m in NEEDED.items() if importlib.util.find_spec(m) is None}
    found = {_wheel_dist(w): w for w in sorted(wheels.glob("*.whl"))} if wheels.is_dir() else {}
    lacking = sorted(set(want) - set(found))
    if lacking:
        raise SystemExit(f"the device lacks {lacking} and {wheels} has no wheel of them: run "
                         "python scripts/device.py prepare before the draw")
    return [found[d] for d in sorted(want)]


def _tree_bytes(folder: pathlib.Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def prepare(records: pathlib.Path, out: pathlib.Path, images: int, val_images: int,
            wheels: bool) -> None:
    """The carry: a JPEG subset of ``records`` (``out/records``) and the wheels of
    :data:`NEEDED` for the device's Python (``out/wheels``), checked to fit one call with the
    working tree (the run of :data:`RUN` included)."""
    from gpu_detector import subset

    if not (records / "objects.json").exists():
        raise SystemExit(f"{records} is not a records folder (no objects.json): pass the "
                         "records of a train.adapt or train.campaign run")
    refiner = f"the device's refiner ({CONFIG}, {' '.join(CONFIG_OVERRIDES)})"
    state = state_bytes()
    if state > RUN_LIMIT:
        raise SystemExit(f"{refiner} has a {state / 2**20:.0f} MiB training state, over the "
                         f"{RUN_LIMIT >> 20} MiB a call brings back: choose a smaller size in "
                         "scripts/device.py")
    step = step_bytes()
    if step > MEMORY_LIMIT:
        raise SystemExit(f"{refiner} needs {step / 2**30:.1f} GiB a train step, over the "
                         f"{MEMORY_LIMIT >> 30} GiB planned for the device: lower the batch or "
                         "the crop size in scripts/device.py")
    meshes = [ROOT.parent / "shared" / "meshes" / "bop" / "tless" / "models" /
              f"obj_{obj_id:06d}.ply" for obj_id in BENCH_MESHES]
    if not all(m.is_file() for m in meshes):
        raise SystemExit(f"the refiner's benchmark meshes {[str(m) for m in meshes]} are "
                         "missing: prepare runs beside ../shared")
    if out.exists():
        if any(out.iterdir()) and not (out / "records" / "objects.json").exists():
            raise SystemExit(f"{out} exists and is not a carry of this command: pass a new "
                             "--out (it is emptied first)")
        shutil.rmtree(out)
    subset(records, out / "records", images, val_images, quality=80)
    # The refiner's MFU benchmark renders T-LESS obj 4-7 (../shared does not travel).
    (out / "meshes").mkdir()
    for m in meshes:
        shutil.copy2(m, out / "meshes" / m.name)
    if wheels:
        platforms = [a for p in ("manylinux_2_28", "manylinux_2_27", "manylinux_2_17",
                                 "manylinux2014", "manylinux1") for a in ("--platform",
                                                                          p + "_x86_64")]
        subprocess.run([sys.executable, "-m", "pip", "download", "--quiet", "--no-deps",
                        "--only-binary=:all:", "--python-version", DEVICE_PYTHON,
                        "--implementation", "cp", *platforms, "--dest", str(out / "wheels"),
                        *NEEDED], check=True)
    size, tree = _tree_bytes(out), _working_tree_bytes()
    print(f"{out}: {size / 2**20:.1f} MiB (the working tree {tree / 2**20:.1f} MiB)", flush=True)
    if size + tree > CALL_LIMIT:
        raise SystemExit(f"{out} is {size / 2**20:.1f} MiB, and with the working tree "
                         f"({tree / 2**20:.1f} MiB) over the {CALL_LIMIT >> 20} MiB a call "
                         "carries: pass fewer --images")


def _working_tree_bytes() -> int:
    """Bytes of the files git would send with a call (tracked and untracked, not ignored)."""
    names = subprocess.run(["git", "ls-files", "-z", "--cached", "--others",
                            "--exclude-standard"], cwd=ROOT, capture_output=True,
                           check=True).stdout.split(b"\0")
    return sum((ROOT / n.decode()).stat().st_size for n in names
               if n and (ROOT / n.decode()).is_file())


def _value(text: str):
    """A config override's value as the launcher parses it: bool (any case), int, float or
    string."""
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def _overrides(overrides: tuple[str, ...], prefix: str) -> dict:
    """The ``--config.<prefix>K=V`` entries of ``overrides`` as {K: value}."""
    pairs = (o.removeprefix("--config.").split("=", 1) for o in overrides)
    return {k.removeprefix(prefix): _value(v) for k, v in pairs if k.startswith(prefix)}


def _refiner_config(config: str, overrides: tuple[str, ...], dtype: str):
    from threept_jax.models.configs import get_refiner_config

    return get_refiner_config(config, **{"dtype": dtype, **_overrides(overrides, "model.")})


@functools.lru_cache(maxsize=4)
def state_bytes(config: str = CONFIG, overrides: tuple[str, ...] = CONFIG_OVERRIDES) -> int:
    """Bytes of a refiner's training state in float32: parameters and Adam's two moments."""
    import jax
    import numpy as np
    from flax import nnx

    from threept_jax.models.refiner import Refiner

    cfg = _refiner_config(config, overrides, "float32")
    shapes = nnx.state(nnx.eval_shape(lambda: Refiner(cfg, rngs=nnx.Rngs(0))), nnx.Param)
    return 3 * 4 * sum(int(np.prod(x.shape)) for x in jax.tree.leaves(shapes))


@functools.lru_cache(maxsize=4)
def step_bytes(config: str = CONFIG, overrides: tuple[str, ...] = CONFIG_OVERRIDES) -> int:
    """Bytes one bfloat16 train step of the refiner needs on one device, every parameter
    trained (the fine-tuning stage): ``Refiner.memory_plan``'s total at the batch and the
    hypotheses of the config (from shapes only, no compute)."""
    from threept_jax.models.refiner import memory_plan
    from train.configs.refiner import get_config

    train_config = get_config(config)
    batch = _overrides(overrides, "").get("batch_size", train_config.batch_size)
    hypotheses = _overrides(overrides, "data.").get("num_hypotheses",
                                                     train_config.data.num_hypotheses)
    cfg = _refiner_config(config, overrides, "bfloat16")
    return memory_plan(cfg, instances=batch, hypotheses=hypotheses)["total"]


def _environment() -> dict:
    import jax

    versions = {}
    for name in ("jax", "jaxlib", "flax", "optax", "orbax-checkpoint", *NEEDED):
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    devices = jax.devices()
    return {"python": sys.version.split()[0], "packages": versions,
            "backend": jax.default_backend(), "device_kind": devices[0].device_kind,
            "devices": len(devices)}


def _stage(command: list[str], log: pathlib.Path, seconds: float, env: dict) -> int:
    """Run ``command`` (appending its output to ``log``); SIGTERM at ``seconds``, then a
    minute to save and exit before SIGKILL. Returns its exit status."""
    with log.open("a") as f:
        f.write(f"$ {' '.join(command)}\n")
        f.flush()
        proc = subprocess.Popen(command, stdout=f, stderr=subprocess.STDOUT, env=env, cwd=ROOT)
        try:
            return proc.wait(timeout=max(seconds, 1))
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGTERM)
            try:
                return proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                proc.kill()
                return proc.wait()


def _checkpoint_steps(workdir: pathlib.Path) -> list[int]:
    from threept_jax.data.run_dir import RunDir

    return RunDir(workdir, model="refiner").checkpoint_steps()


def _frozen(workdir: pathlib.Path) -> bool:
    """Whether the run in ``workdir`` is the plan's frozen stage (its stem held fixed)."""
    from threept_jax.data.run_dir import RunDir

    return RunDir(workdir, model="refiner").read_config().get("optim", {}).get("freeze") == "stem"


def _pack(workdir: pathlib.Path, out: pathlib.Path) -> int:
    """The run folder with its last checkpoint only (the next draw resumes it; which step is
    best is measured here, on held-out data), gzipped, in parts of :data:`PART_BYTES`
    (``run.tar.gz.NN``). Returns its bytes."""
    steps = _checkpoint_steps(workdir)
    keep = {str(steps[-1])} if steps else set()

    def kept(info: tarfile.TarInfo) -> tarfile.TarInfo | None:
        parts = info.name.split("/")
        old = (len(parts) >= 3 and parts[1] == "checkpoints" and parts[2].isdigit()
               and parts[2] not in keep)
        return None if old else info

    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        tar.add(workdir, arcname="run", filter=kept)
    data = buf.getvalue()
    for i in range(0, len(data), PART_BYTES):
        (out / f"run.tar.gz.{i // PART_BYTES:02d}").write_bytes(data[i:i + PART_BYTES])
    return len(data)


def run(minutes: float, carry: pathlib.Path, out: pathlib.Path, dry_run: bool,
        mfu: bool = True, resume: pathlib.Path = RUN) -> dict:
    """Every stage of the device's call (module docstring) within ``minutes`` of wall time
    from now, writing to ``out``; ``mfu=False`` skips the MFU table (a device kind measured
    before: every minute trains); training goes on from the run in ``resume`` if any."""
    start = time.monotonic()
    deadline = start + minutes * 60
    records = carry / "records"
    if not (records / "objects.json").exists():
        raise SystemExit(f"{records} holds no records: run python scripts/device.py prepare "
                         "and carry its folder")
    out.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        p for p in (os.environ.get("PYTHONPATH"), str(ROOT)) if p), "PYTHONUNBUFFERED": "1"}
    summary: dict = {"dry_run": dry_run, "minutes": {}}
    (out / "env.json").write_text(json.dumps(_environment(), indent=1))

    # (a) The MFU table, once per device kind: at most MFU_SHARE of the call, half each.
    if mfu:
        t = time.monotonic()
        detector = ["tiny"] if dry_run else ["S/16", "B/16"]
        refiner = [DRY_CONFIG] if dry_run else [CONFIG, "paper"]
        steps = ["--steps", "1", "--batch", "2"] if dry_run else ["--steps", "3"]
        summary["mfu_status"] = []
        for i, command in enumerate((
                [sys.executable, "bench/train_step.py", "--variants", *detector, *steps],
                [sys.executable, "bench/refiner_step.py", "--variants", *refiner, *steps,
                 "--models", str(carry / "meshes"), "--records", str(records),
                 "--data-examples", "4" if dry_run else "256"])):
            left = start + minutes * 60 * MFU_SHARE * (i + 1) / 2 - time.monotonic()
            summary["mfu_status"].append(_stage(command, out / "mfu.txt", left, env)
                                         if left > 10 else "skipped: no time left")
        summary["minutes"]["mfu"] = (time.monotonic() - t) / 60

    # (b) Training to the deadline, resumed from the last draw's run: the frozen stage to its
    # last step, then (in the same draw when time is left) the fine-tuning stage.
    t = time.monotonic()
    workdir = pathlib.Path(tempfile.mkdtemp(prefix="device_run_")) / "run"
    if resume.is_dir():
        shutil.copytree(resume, workdir)
    frozen_steps = DRY_FROZEN_STEPS if dry_run else FROZEN_STEPS
    pack_seconds = 90  # up to 60 s for the SIGTERM save, then the packing
    summary["train"], stage, init_from = [], "frozen", None
    found = _checkpoint_steps(workdir)
    if found and not _frozen(workdir):
        stage = "fine-tune"  # resumed
    elif found and found[-1] >= frozen_steps:
        # The frozen stage ended with the last draw: fine-tuning starts from it.
        stage, init_from, workdir = "fine-tune", workdir, workdir.with_name("fine-tune")
    while True:
        before = (_checkpoint_steps(workdir) or [0])[-1]
        if stage == "frozen":
            total = frozen_steps
        else:
            total = before + 2 if dry_run else PLAN_STEPS - frozen_steps
        command = [sys.executable, "train/launch.py",
                   f"--config=train/configs/refiner.py:{DRY_CONFIG if dry_run else CONFIG}",
                   f"--workdir={workdir}", f"--config.data_dir={records.resolve()}",
                   f"--config.total_steps={total}", "--config.progress_bar=False",
                   "--config.checkpoint.async_save=False",
                   # The carry's absolute path may differ between draws; its records must not
                   # (the saved data iterator indexes them): a new records subset is a new run.
                   "--allow_config_change", *STAGES[stage]]
        if init_from is not None:
            command.append(f"--config.init_from={init_from}")
        if dry_run:
            command += DRY_OVERRIDES
        else:
            command += [*CONFIG_OVERRIDES, "--config.checkpoint.every_steps=250",
                        "--config.eval.every_steps=1000",
                        f"--config.data.num_workers={max(1, min(12, (os.cpu_count() or 2) - 2))}"]
        began = time.monotonic()
        status = _stage(command, out / "train.log", deadline - pack_seconds - began, env)
        summary["train"].append({"stage": stage, "workdir": str(workdir), "status": status,
                                 "steps_before": before,
                                 "steps_after": (_checkpoint_steps(workdir) or [0])[-1],
                                 "minutes": (time.monotonic() - began) / 60})
        left = deadline - pack_seconds - time.monotonic()
        if (stage == "fine-tune" or status != 0 or summary["train"][-1]["steps_after"]
                < frozen_steps or left < MIN_STAGE_SECONDS):
            break
        stage, init_from, workdir = "fine-tune", workdir, workdir.with_name("fine-tune")
    if not _checkpoint_steps(workdir) and init_from is not None:
        workdir = init_from  # the fine-tuning stage saved nothing: the frozen run goes back
    summary["minutes"]["train"] = (time.monotonic() - t) / 60

    # (c) What comes back.
    summary["run_bytes"] = _pack(workdir, out) if workdir.is_dir() else 0
    if summary["run_bytes"] > RUN_LIMIT:
        summary["error"] = (f"the run packs to {summary['run_bytes'] / 2**20:.0f} MiB, over the "
                            f"{RUN_LIMIT >> 20} MiB a call brings back: train a smaller size")
    summary["minutes"]["total"] = (time.monotonic() - start) / 60
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary), flush=True)
    return summary


def unpack(files: pathlib.Path, to: pathlib.Path) -> None:
    """The run a device call brought back (``run.tar.gz.NN`` under ``files``) into ``to``."""
    parts = sorted(files.rglob("run.tar.gz.*"))
    if not parts:
        raise SystemExit(f"no run.tar.gz.NN under {files}: pass the folder the run tool "
                         "copied the call's files to")
    data = b"".join(p.read_bytes() for p in parts)
    staging = to.with_name(to.name + ".partial")
    if staging.exists():
        shutil.rmtree(staging)
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
        tar.extractall(staging, filter="data")
    if to.exists():
        shutil.rmtree(to)
    (staging / "run").rename(to)
    staging.rmdir()
    print(f"{to}: steps {_checkpoint_steps(to)}; held-out figures: python -m train.eval_refiner "
          f"--workdir {to}; shipped as the default refiner only if it refines held-out scenes "
          f"better: python -m train.ship --run {to} --name NAME --dataset-dir HELD_OUT",
          flush=True)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="python scripts/device.py",
                                description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("prepare", help="the carry of a draw (here)")
    s.add_argument("--records", type=pathlib.Path, required=True,
                   help="records folder of the training data (a train.adapt or campaign run's)")
    s.add_argument("--out", type=pathlib.Path, default=pathlib.Path(".device"))
    s.add_argument("--images", type=int, default=200,
                   help="training images carried (200 JPEGs of 640 x 480: about 12 MB)")
    s.add_argument("--val-images", type=int, default=16, help="held-out images carried")
    s.add_argument("--no-wheels", dest="wheels", action="store_false",
                   help="carry no wheels (a device that has every package)")
    m = sub.add_parser("missing", help="the carried wheels this Python needs (the device)")
    m.add_argument("--wheels", type=pathlib.Path, required=True)
    r = sub.add_parser("run", help="every stage of the device's call (the device)")
    r.add_argument("--minutes", type=float, required=True, help="wall time of the call")
    r.add_argument("--carry", type=pathlib.Path, default=pathlib.Path(".device"))
    r.add_argument("--out", type=pathlib.Path, default=None, help="default: $OUT")
    r.add_argument("--dry-run", action="store_true", help="tiny sizes, two steps (CPU tests)")
    r.add_argument("--no-mfu", dest="mfu", action="store_false",
                   help="skip the MFU table (measured on this device kind before)")
    r.add_argument("--resume", type=pathlib.Path, default=RUN, help="the last draw's run")
    u = sub.add_parser("unpack", help="the run a call brought back (here)")
    u.add_argument("--files", type=pathlib.Path, required=True)
    u.add_argument("--to", type=pathlib.Path, default=RUN)
    args = p.parse_args(argv)
    if args.command == "prepare":
        prepare(args.records, args.out, args.images, args.val_images, args.wheels)
    elif args.command == "missing":
        print(" ".join(str(w) for w in missing(args.wheels)))
    elif args.command == "run":
        out = args.out or (pathlib.Path(os.environ["OUT"]) if os.environ.get("OUT") else None)
        if out is None:
            p.error("run needs --out or $OUT")
        run(args.minutes, args.carry, out, args.dry_run, args.mfu, args.resume)
    else:
        unpack(args.files, args.to)


if __name__ == "__main__":
    main()
