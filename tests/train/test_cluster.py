"""Training on a cluster: config keys checked up front, SIGTERM, several processes, run dirs."""

import dataclasses
import json
import signal
import socket
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from fixtures.training import ROOT, STEPS, SUBPROCESS_ENV, launch_args, small_config

from threept_jax.data.run_dir import RunDir
from threept_jax.models.configs import DetectorConfig
from train import run_config
from train import trainer_detector as td
from train.configs import detector as detector_configs


def _assert_same_batch(a, b):
    assert set(a) == set(b)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


# --------------------------------------------------------------------------- config keys

BAD_KEYS = ("model.num_prior_view", "loss.giou_weigth", "data.max_instance", "eval.evry_steps")
BAD_CONFIG = '''from train.configs.detector import get_config as tiny


def get_config(arg="tiny"):
    c = tiny(arg)
    c.{section}.{key} = 1
    return c
'''


def test_unknown_config_keys_stop_the_launcher_before_compiling(tmp_path):
    """A typo in a model, loss, data or eval key, on the command line or in a config file:
    exit code 2, one stderr line naming the key and the section's valid keys, no traceback,
    nothing written to the workdir (so nothing ran: the trainer writes its run files first)."""
    runs = {}
    for key in BAD_KEYS:
        section, name = key.split(".")
        work = tmp_path / f"cli_{section}"
        args = launch_args(small_config(tmp_path / "no_data"), work, [f"--config.{key}=1"])
        runs[("cli", key)] = (work, subprocess.Popen(
            args, env=SUBPROCESS_ENV, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True))
        cfg_file = tmp_path / f"bad_{section}.py"
        cfg_file.write_text(BAD_CONFIG.format(section=section, key=name))
        work = tmp_path / f"file_{section}"
        runs[("file", key)] = (work, subprocess.Popen(
            [sys.executable, str(ROOT / "train" / "launch.py"), "--config", f"{cfg_file}:tiny",
             "--workdir", str(work), f"--config.data_dir={tmp_path / 'no_data'}"],
            env=SUBPROCESS_ENV, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True))
    for (where, key), (work, proc) in runs.items():
        out, err = proc.communicate(timeout=120)
        section = key.split(".")[0]
        assert proc.returncode == 2, (where, key, proc.returncode, err[-2000:])
        lines = err.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in err, (where, key, err[-2000:])
        assert f"unknown config key '{key}'" in lines[0], (where, lines[0])
        # The valid keys of the section are named (from the dataclass, e.g. DetectorConfig).
        for valid in run_config.valid_keys(section):
            assert valid in lines[0], (where, key, valid)
        assert not work.exists(), (where, key)


def test_every_detector_field_can_be_set_from_the_config(monkeypatch):
    """Each DetectorConfig field, set to a non-default value in the config, reaches the built
    dataclass (no hand-copied field list that can drop one)."""
    other = {
        "variant": "S/16", "image_size": 256, "render_size": 64, "num_prior_views": 6,
        "tokens_per_view": 2, "embed_dim": 96, "num_registers": 4, "posemb": "sincos2d",
        "share_backbone": False, "attention_impl": "xla", "box_head_layers": 2,
        "presence_head_layers": 3, "class_prior": 0.05, "logit_scale_init": 5.0, "remat": True,
        "stem": "conv", "dtype": "bfloat16", "param_dtype": "bfloat16",
    }
    fields = [f.name for f in dataclasses.fields(DetectorConfig)]
    assert sorted(other) == sorted(fields), "give the new DetectorConfig field a test value"
    defaults = DetectorConfig()
    for name in fields:
        c = detector_configs.get_config("tiny")
        c.model[name] = other[name]
        built = run_config.model_config(c)
        value = getattr(built, name)
        expected = jnp.dtype(other[name]) if name.endswith("dtype") else other[name]
        assert value == expected != getattr(defaults, name), name
    # On the command line too, for fields the config file does not mention (a typed None
    # default such as embed_dim included).
    from absl import flags
    from ml_collections import config_flags

    argv = ["launch.py", f"--config={ROOT / 'train' / 'configs' / 'detector.py'}:tiny",
            "--config.model.num_prior_views=6", "--config.model.embed_dim=96",
            "--config.model.attention_impl=xla"]
    monkeypatch.setattr(sys, "argv", argv)  # ml_collections reads the overrides from sys.argv
    fv = flags.FlagValues()
    config_flags.DEFINE_config_file("config", None, "", flag_values=fv, lock_config=True)
    fv(argv)
    built = run_config.model_config(fv.config)
    assert (built.num_prior_views, built.embed_dim, built.attention_impl) == (6, 96, "xla")
    # The other sections are exactly their dataclasses' fields, at the defaults unless the
    # config overrides them.
    c = detector_configs.get_config("tiny")
    assert run_config.loss_config(c) == dataclasses.replace(
        type(run_config.loss_config(c))(), matches_per_target=4)
    ex = run_config.example_config(c, split="train", num_templates=16)
    assert (ex.tile_size, ex.render_size, ex.max_instances) == (128, 32, 8)
    c.data.scale_reference = 256
    assert run_config.example_config(c, split="val", num_templates=0).scale_reference == 256


# --------------------------------------------------------------------------- SIGTERM


def test_sigterm_saves_exits_zero_and_resumes_to_the_same_batch(toy, tmp_path):
    """SIGTERM between two checkpoint intervals: the run saves the step it reached, exits 0,
    and a resumed trainer reads the same next batch and gets the same loss as an uninterrupted
    run."""
    workdir = tmp_path / "term"
    cfg = small_config(toy, total_steps=1000, **{"checkpoint.every_steps": 500})
    proc = subprocess.Popen(launch_args(cfg, workdir), env=SUBPROCESS_ENV, cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        # log_every=1: "step N/total:" lines on stdout; signal once two steps have been logged.
        seen = []
        deadline = time.time() + 240
        for line in proc.stdout:
            seen.append(line)
            if line.startswith("step 2/"):
                break
            assert time.time() < deadline, "no step 2 within 4 minutes"
        else:
            raise AssertionError("training exited early:\n" + "".join(seen[-30:]))
        proc.send_signal(signal.SIGTERM)
        t0 = time.time()
        rest, _ = proc.communicate(timeout=60)
        stop_s = time.time() - t0
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == 0, "".join(seen[-10:]) + rest[-3000:]
    assert "stopped by SIGTERM" in rest and stop_s < 60
    steps = RunDir(workdir).checkpoint_steps()
    assert len(steps) == 1 and 2 <= steps[0] < 500, steps  # saved on SIGTERM, not on schedule
    k = steps[0]
    ref = td.DetectorTrainer(cfg, tmp_path / "ref", devices=jax.devices()[:1], step_cache=STEPS)
    for _ in range(k):
        ref.train_step(ref.next_batch())
    ref_batch = ref.next_batch()
    ref_loss = float(ref.train_step(ref_batch)["loss"])
    ref.close()
    resumed = td.DetectorTrainer(cfg, workdir, devices=jax.devices()[:1], step_cache=STEPS)
    assert resumed.start_step == k
    batch = resumed.next_batch()
    _assert_same_batch(batch, ref_batch)
    assert float(resumed.train_step(batch)["loss"]) == pytest.approx(ref_loss, rel=1e-5)
    resumed.close()


# --------------------------------------------------------------------------- processes


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_processes_train_like_one_and_restore(toy, tmp_path):
    """Two CPU processes started like a Kubernetes indexed Job (JAX_COORDINATOR_ADDRESS,
    JAX_NUM_PROCESSES, JOB_COMPLETION_INDEX; gloo collectives, one device each, per-process data
    slices) give the loss of one process running the same global batches on two devices, for
    two steps by hand, a checkpoint written by both, and the steps after both restored it, up
    to the step both saved when one of them got SIGTERM (JAX's preemption service)."""
    cfg = small_config(toy, total_steps=1000, **{"mesh.data": -1, "checkpoint.every_steps": 500})
    cfg_file = tmp_path / "config.json"
    cfg_file.write_text(cfg.to_json())
    port = _free_port()
    procs = [subprocess.Popen(
        [sys.executable, str(ROOT / "tests" / "train" / "multiprocess_worker.py"),
         str(cfg_file), str(tmp_path / "multi"), str(tmp_path / f"p{i}.npz")],
        env={**SUBPROCESS_ENV, "JAX_COORDINATOR_ADDRESS": f"127.0.0.1:{port}",
             "JAX_NUM_PROCESSES": "2", "JOB_COMPLETION_INDEX": str(i)},
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for i in range(2)]
    try:
        outs = [p.communicate(timeout=300)[0] for p in procs]
    finally:
        for p in procs:
            p.kill()
            p.wait()
    for p, out in zip(procs, outs, strict=True):
        assert p.returncode == 0, out[-4000:]
    parts = [np.load(tmp_path / f"p{i}.npz") for i in range(2)]
    last = int(parts[0]["preempted"])
    assert int(parts[1]["preempted"]) == last and 3 <= last < 500
    assert RunDir(tmp_path / "multi").checkpoint_steps() == [2, last]
    np.testing.assert_array_equal(parts[0]["losses"], parts[1]["losses"])
    # The processes read different records (per-process slices of the data).
    assert not np.array_equal(parts[0]["step1/image"], parts[1]["step1/image"])
    # Reference: one process, two devices, the concatenated global batches.
    ref = td.DetectorTrainer(small_config(toy, total_steps=1000, **{"mesh.data": 2}),
                             tmp_path / "one", devices=jax.devices()[:2], step_cache=STEPS)
    for step in range(1, last + 1):
        batch = {k: np.concatenate([p[f"step{step}/{k}"] for p in parts]) for k in td.STEP_FIELDS}
        loss = float(ref.train_step(batch)["loss"])
        assert loss == pytest.approx(float(parts[0]["losses"][step - 1]), rel=1e-5), step
    ref.close()


# --------------------------------------------------------------------------- run directory


def test_resuming_another_model_names_the_run(toy, tmp_path):
    run = RunDir(tmp_path)
    run.write_model_config(DetectorConfig(variant="tiny/8", image_size=64, render_size=32))
    run.check_same_model(DetectorConfig(variant="tiny/8", image_size=64, render_size=32,
                                        dtype="bfloat16", remat=True))  # compute only: fine
    with pytest.raises(ValueError, match=r"this workdir holds a tiny/8 run .* S/16: .*"
                                         r"variant='tiny/8' \(config: 'S/16'\)"):
        run.check_same_model(DetectorConfig(variant="S/16", image_size=64, render_size=32))
    assert json.loads(run.model_file.read_text())["variant"] == "tiny/8"
    # A run saved before a model field existed resumes under the field's default, not another.
    fields = json.loads(run.model_file.read_text())
    del fields["num_registers"]
    run.model_file.write_text(json.dumps(fields))
    run.check_same_model(DetectorConfig(variant="tiny/8", image_size=64, render_size=32))
    with pytest.raises(ValueError, match=r"num_registers=0 \(config: 1\)"):
        run.check_same_model(DetectorConfig(variant="tiny/8", image_size=64, render_size=32,
                                            num_registers=1))
    run.write_model_config(DetectorConfig(variant="tiny/8", image_size=64, render_size=32))
    assert run.checkpoint_steps() == []
    with pytest.raises(FileNotFoundError, match="saved none yet"):
        run.resolve_step("best")
    # The trainer refuses before building anything: a tiny/16 config on the tiny/8 run.
    (run.checkpoint_dir / "5").mkdir(parents=True)
    (run.checkpoint_dir / "5" / "commit_success.txt").write_text("")
    assert run.checkpoint_steps() == [5]
    cfg = small_config(toy, **{"model.variant": "tiny/16"})
    with pytest.raises(ValueError, match="this workdir holds a tiny/8 run"):
        td.DetectorTrainer(cfg, tmp_path, devices=jax.devices()[:1], step_cache=STEPS)
    assert json.loads(run.model_file.read_text())["variant"] == "tiny/8"  # not overwritten


def _imports(path) -> set[str]:
    """Every module a file imports, at any depth (function-level imports included)."""
    import ast

    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            out |= {node.module} | {f"{node.module}.{a.name}" for a in node.names}
    return out


def test_no_import_cycle_and_train_infer_apart():
    """The evaluator builds its configs from train.run_config, not the trainer; training and
    inference share the run-directory format through threept_jax.data.run_dir only."""
    assert not {m for m in _imports(ROOT / "train" / "eval_detector.py")
                if m.startswith("train.trainer_detector")}
    assert not {m for m in _imports(ROOT / "train" / "run_config.py") if m.startswith("train")}
    # The evaluation runs inference's detection through threept_jax.pipeline, not infer. The
    # adaptation command (and the fit of the templates detector's score on its candidates)
    # alone orchestrate datagen, training and inference (docs/architecture.md); only the demo,
    # the second (for the adaptation's scenes) and the shipping of a refiner (its held-out
    # check on the inference path) import the first. The candidates and the per-part fit both
    # use (train/cell_score.py) import neither; the verifier's training
    # (train/templates_verifier.py) makes its cells as the adaptation makes them.
    for path in (ROOT / "train").rglob("*.py"):
        if path.name in ("adapt.py", "templates_score.py", "cell_score.py", "ship.py",
                         "templates_verifier.py"):
            continue
        assert not {m for m in _imports(path) if m == "infer" or m.startswith("infer.")}, path
    for package in ("train", "infer", "threept_jax", "datagen"):
        for path in (ROOT / package).rglob("*.py"):
            assert "train.templates_score" not in _imports(path), path
            assert "train.ship" not in _imports(path), path
            if path.name not in ("templates_score.py", "ship.py", "templates_verifier.py"):
                assert "train.adapt" not in _imports(path), path
    infer_imports = _imports(ROOT / "infer" / "checkpoint.py")
    assert not {m for m in infer_imports if m == "train" or m.startswith("train.")}
    assert "threept_jax.data.run_dir" in infer_imports
    assert "threept_jax.data.run_dir" in _imports(ROOT / "train" / "checkpointing.py")
