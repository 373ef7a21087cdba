"""``scripts/device_run.sh`` and ``scripts/device.py`` (issue 40), the lent GPU's one command,
dry-run on CPU. Covered: the carry, the wheels installed only for modules the device lacks,
every stage at the tiny size, what comes back, and a second draw that resumes the first
draw's run. Its dry run trains through ``train/launch.py``, so it also checks what the
launcher writes for the refiner: loaded by inference with its step options (the evaluation
command on a run directory: tests/train/test_refiner_trainer.py)."""

import importlib.util
import json
import pathlib
import subprocess
import sys

import jax
import numpy as np
import pytest
from fixtures.refiner_records import write_refiner_records
from fixtures.training import ROOT, SUBPROCESS_ENV
from flax import nnx

import infer
from infer.checkpoint import load_refiner
from threept_jax.data.pretrained import stem_params
from threept_jax.data.run_dir import RunDir


def _device():
    spec = importlib.util.spec_from_file_location("device", ROOT / "scripts" / "device.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_only_the_wheels_of_missing_modules_are_installed(tmp_path, monkeypatch):
    device = _device()
    monkeypatch.setattr(device, "NEEDED", {"numpy": "numpy", "no-such-dist": "no_such_module_x"})
    wheels = tmp_path / "wheels"
    wheels.mkdir()
    (wheels / "numpy-2.0.0-cp312-cp312-manylinux2014_x86_64.whl").write_bytes(b"")
    with pytest.raises(SystemExit, match=r"lacks \['no-such-dist'\].*device.py prepare"):
        device.missing(wheels)
    wheel = wheels / "no_such_dist-1.0-py3-none-any.whl"
    wheel.write_bytes(b"")
    assert device.missing(wheels) == [wheel]  # numpy is importable here: not installed


def test_bad_input_names_the_fix(tmp_path, monkeypatch):
    device = _device()
    with pytest.raises(SystemExit, match="not a records folder"):
        device.prepare(tmp_path, tmp_path / "carry", 4, 2, wheels=False)
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("a user's file")
    with pytest.raises(SystemExit, match="no run.tar.gz.NN"):
        device.unpack(tmp_path, tmp_path / "run")
    with pytest.raises(SystemExit, match="holds no records.*device.py prepare"):
        device.run(1.0, tmp_path / "nothing", tmp_path / "out", dry_run=True)
    assert not (tmp_path / "out").exists()  # refused before any work or output
    records = write_refiner_records(tmp_path / "rec", num_objects=2, mesh_seed=0, num_images=4,
                                    splits=("train", "val"), max_faces=600)
    with pytest.raises(SystemExit, match="is not a carry of this command"):
        device.prepare(records, tmp_path / "mine", 4, 2, wheels=False)
    assert (tmp_path / "mine" / "notes.txt").exists()  # nothing of the user's is deleted
    monkeypatch.setattr(device, "CALL_LIMIT", 1000)
    with pytest.raises(SystemExit, match="over the 0 MiB a call carries: pass fewer --images"):
        device.prepare(records, tmp_path / "carry", 4, 2, wheels=False)
    limit = device.RUN_LIMIT
    monkeypatch.setattr(device, "RUN_LIMIT", 1000)  # a refiner whose state cannot come back
    with pytest.raises(SystemExit, match="MiB training state, over the 0 MiB a call brings"):
        device.prepare(records, tmp_path / "carry", 4, 2, wheels=False)
    monkeypatch.setattr(device, "RUN_LIMIT", limit)
    monkeypatch.setattr(device, "MEMORY_LIMIT", 2**30)  # a step the device cannot hold
    with pytest.raises(SystemExit, match=r"needs \d+\.\d GiB a train step, over the 1 GiB.*lower"):
        device.prepare(records, tmp_path / "carry", 4, 2, wheels=False)


def test_a_dry_run_trains_packs_and_the_next_draw_resumes_it(tmp_path, monkeypatch):
    records = write_refiner_records(tmp_path / "rec", num_objects=2, mesh_seed=0, num_images=6,
                                    splits=("train", "val"), max_faces=600)
    carry = tmp_path / "carry"
    env = {**SUBPROCESS_ENV, "PYTHON": sys.executable, "DEVICE_CARRY": str(carry)}

    def device(*argv):
        proc = subprocess.run([sys.executable, "scripts/device.py", *argv], cwd=ROOT, env=env,
                              capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr[-3000:]

    run = tmp_path / "models" / "refiner-gpu-run"

    def draw(out, *flags):
        proc = subprocess.run(["bash", "scripts/device_run.sh", "10", "--dry-run", "--resume",
                               str(run), *flags],
                              cwd=ROOT, env={**env, "OUT": str(out)}, capture_output=True,
                              text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
        return json.loads((out / "summary.json").read_text())

    device("prepare", "--records", str(records), "--out", str(carry), "--images", "4",
           "--val-images", "2", "--no-wheels")
    first = draw(tmp_path / "out1")
    assert first["mfu_status"] == [0, 0]
    # The plan's two stages in one draw: the stem frozen to its last step, then fine-tuning.
    frozen, tuned = first["train"]
    assert [(s["stage"], s["status"], s["steps_before"], s["steps_after"])
            for s in first["train"]] == [("frozen", 0, 0, 2), ("fine-tune", 0, 0, 2)]
    assert sum(s["minutes"] for s in first["train"]) <= first["minutes"]["train"]
    env_json = json.loads((tmp_path / "out1" / "env.json").read_text())
    assert env_json["backend"] == "cpu" and env_json["packages"]["jax"]
    mfu = (tmp_path / "out1" / "mfu.txt").read_text()
    assert mfu.count("x the matmul reference") == 2  # 3PT-D's step and 3PT-R's, both timed
    assert "tiny data: one thread makes" in mfu  # the carried records against the step
    # The frozen stage's stem after its train steps is the converted ALIKED, exactly
    # (test_aliked checks that against upstream's outputs); its token projection has moved.
    aliked = jax.tree.leaves(stem_params("aliked"))
    model = load_refiner(frozen["workdir"])[0]
    for got, want in zip(jax.tree.leaves(nnx.to_pure_dict(nnx.state(model.stem, nnx.Param))),
                         aliked, strict=True):
        np.testing.assert_array_equal(np.asarray(got), want)
    assert np.any(np.asarray(model.stem_tokens.kernel[...]))
    device("unpack", "--files", str(tmp_path / "out1"), "--to", str(run))
    # What came back is the fine-tuning run, an ordinary 3PT-R run that the launcher wrote,
    # started from the frozen one: inference loads it with the step options it was trained
    # with.
    assert RunDir(run, model="refiner").checkpoint_steps() == [2]  # the last one only
    config = RunDir(run, model="refiner").read_config()
    assert config["optim"]["freeze"] == "" and config["init_from"] == frozen["workdir"]
    assert json.loads((run / "refiner.json").read_text())["variant"] == "tiny/16"
    model, cfg, step, settings = load_refiner(run)
    assert step == 2 and cfg.variant == "tiny/16" and cfg.pretrained_stem == "aliked"
    assert cfg.stem_descriptors and cfg.descriptor_dim == 128
    stem = jax.tree.leaves(nnx.to_pure_dict(nnx.state(model.stem, nnx.Param)))
    assert any(np.any(np.asarray(got) != want) for got, want in zip(stem, aliked, strict=True))
    assert settings.num_matches == 16 and settings.max_faces == 256
    out = model(np.zeros((1, 1, 64, 64, 3), np.uint8), np.zeros((1, 2, 1, 64, 64, 3), np.uint8))
    assert out["scores"].shape == (1, 2)
    models = infer.load(refiner=run)
    assert models.detector is None and models.refiner_step == 2
    assert models.refine_settings == settings

    # The next draws find the run where unpack put it: the launcher (whose resume test_resume
    # covers) is started in a workdir holding it, to go on from its last step in its stage.
    module, seen = _device(), []

    def stage(command, log, seconds, env):
        workdir = pathlib.Path(next(a for a in command if a.startswith("--workdir="))[10:])
        seen.append((command, workdir, RunDir(workdir, model="refiner").checkpoint_steps()))
        return 0

    monkeypatch.setattr(module, "_stage", stage)
    second = module.run(10.0, carry, tmp_path / "out2", dry_run=True, mfu=False, resume=run)
    (command, _, steps), = seen  # the training stage only
    assert command[1] == "train/launch.py" and steps == [2]
    assert "--config.total_steps=4" in command and "--config.optim.freeze=" in command
    assert not any(a.startswith("--config.init_from") for a in command)
    assert [(s["stage"], s["steps_before"]) for s in second["train"]] == [("fine-tune", 2)]
    assert "--allow_config_change" in command  # the carry's path may differ between draws
    assert "mfu_status" not in second and (tmp_path / "out2" / "run.tar.gz.00").exists()
    # A draw that finds the frozen stage at its last step starts fine-tuning from it; one that
    # finds it short goes on with it.
    seen.clear()
    third = module.run(10.0, carry, tmp_path / "out3", dry_run=True, mfu=False,
                       resume=pathlib.Path(frozen["workdir"]))
    (command, workdir, steps), = seen
    assert steps == [] and "--config.optim.freeze=" in command
    assert f"--config.init_from={workdir.with_name('run')}" in command
    assert third["train"][0]["stage"] == "fine-tune"  # it saved nothing: the frozen run goes
    assert third["run_bytes"] > 0  # back
    seen.clear()
    monkeypatch.setattr(module, "DRY_FROZEN_STEPS", 4)
    module.run(10.0, carry, tmp_path / "out4", dry_run=True, mfu=False,
               resume=pathlib.Path(frozen["workdir"]))
    (command, _, steps), = seen
    assert steps[-1] == 2 and "--config.optim.freeze=stem" in command
    assert "--config.total_steps=4" in command
    assert not any(a.startswith("--config.init_from") for a in command)
