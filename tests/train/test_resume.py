"""Resuming a run: config changes refused or recorded, TensorBoard steps shown once, and the
launcher's one-line errors on bad values, a changed config or another model's workdir."""

import json
import os
import shutil
import struct
import subprocess

import jax
import pytest
from fixtures.training import ROOT, STEPS, SUBPROCESS_ENV, launch_args, small_config

from threept_jax.data.run_dir import RunDir
from train import run_config
from train import trainer_detector as td
from train.configs import detector as detector_configs

# --------------------------------------------------------------------------- values

#: (key, bad value): each must be refused by check_config, naming the key.
BAD_VALUES = (
    ("total_steps", 0), ("total_steps", -5), ("batch_size", 0), ("batch_size", -4),
    ("seed", -1), ("log_every", 0), ("distributed", "maybe"),
    ("optim.learning_rate", 0.0), ("optim.learning_rate", -1e-3),
    ("optim.learning_rate", float("nan")), ("optim.learning_rate", float("inf")),
    ("optim.warmup_steps", -1), ("optim.b1", 1.0), ("optim.b2", -0.1),
    ("optim.weight_decay", -0.05), ("optim.grad_clip_norm", 0.0), ("optim.end_lr_factor", -1.0),
    ("eval.every_steps", -100), ("eval.num_examples", 0), ("eval.batch_size", 0),
    ("eval.num_images", 0), ("eval.num_scales", 0), ("eval.candidates_per_object", 0),
    ("eval.num_templates", 0), ("eval.template_chunk", 0), ("eval.max_detections", 0),
    ("eval.nms_iou", 0.0), ("eval.nms_iou", 1.5), ("eval.match_iou", -0.5),
    ("eval.orientation_threshold_deg", 0.0), ("checkpoint.every_steps", -1),
    ("checkpoint.max_to_keep", 0), ("checkpoint.best_mode", "maximum"),
    ("mesh.data", 0), ("mesh.fsdp", -2), ("mesh.fsdp_min_size", -1),
    ("data.num_train_templates", 0), ("data.num_train_records", 0), ("data.num_workers", -1),
    ("data.worker_buffer_size", 0),
)

#: Values at the edge of their range, each with a documented meaning: accepted.
EDGE_VALUES = (
    ("eval.every_steps", 0), ("checkpoint.every_steps", 0), ("mesh.data", -1),
    ("mesh.fsdp", -1), ("data.num_train_records", -1), ("eval.num_templates", -1),
    ("optim.warmup_steps", 0), ("optim.weight_decay", 0.0), ("optim.b1", 0.0),
    ("eval.nms_iou", 1.0), ("distributed", True), ("distributed", "false"), ("seed", 0),
    ("data.num_workers", 0), ("total_steps", 1), ("batch_size", 1),
)


def _set(config, key, value):
    *path, last = key.split(".")
    node = config
    for p in path:
        node = node[p]
    with node.ignore_type():
        node[last] = value


def test_out_of_range_values_are_refused_naming_the_key():
    for key, value in BAD_VALUES:
        c = detector_configs.get_config("tiny")
        _set(c, key, value)
        with pytest.raises(run_config.ConfigError, match=rf"invalid config value: {key}="):
            run_config.check_config(c)
    for key, value in EDGE_VALUES:
        c = detector_configs.get_config("tiny")
        _set(c, key, value)
        run_config.check_config(c)
    # Several bad values: all named in one line.
    c = detector_configs.get_config("tiny")
    c.total_steps, c.optim.learning_rate = 0, -1.0
    with pytest.raises(run_config.ConfigError) as e:
        run_config.check_config(c)
    assert "total_steps=0" in str(e.value) and "optim.learning_rate=-1.0" in str(e.value)
    assert "\n" not in str(e.value)


def test_eval_batch_the_devices_do_not_divide_is_refused_before_training(toy, tmp_path):
    """The evaluator is built at the first evaluation; its batch is checked up front."""
    cfg = small_config(toy, **{"eval.every_steps": 1, "eval.batch_size": 3, "mesh.data": 2})
    with pytest.raises(ValueError, match="eval.batch_size=3 is not divisible by the 2 devices"):
        td.DetectorTrainer(cfg, tmp_path / "w", devices=jax.devices()[:2], step_cache=STEPS)
    assert not (tmp_path / "w").exists()


# --------------------------------------------------------------------------- config changes


def test_resume_config_changes_free_refused_and_absent_keys():
    saved = json.loads(detector_configs.get_config("tiny").to_json_best_effort())
    c = detector_configs.get_config("tiny")
    c.total_steps, c.log_every, c.model.remat = 5000, 7, True  # free: extend, log, compute
    changes, refused = run_config.check_resume_config(saved, c, allow_change=False)
    assert changes == {"total_steps": (1000, 5000), "log_every": (20, 7),
                       "model.remat": (False, True)} and refused == []
    c.seed, c.batch_size, c.optim.learning_rate = 3, 32, 1e-4
    c.data_dir = "/other/records"
    with pytest.raises(run_config.ConfigError) as e:
        run_config.check_resume_config(saved, c, allow_change=False)
    line = str(e.value)
    for text in ("batch_size=16 (now 32)", "data_dir='' (now '/other/records')",
                 "optim.learning_rate=0.001 (now 0.0001)", "seed=0 (now 3)",
                 "--allow_config_change", "config_history.json"):
        assert text in line, (text, line)
    assert "total_steps" not in line and "log_every" not in line
    changes, refused = run_config.check_resume_config(saved, c, allow_change=True)
    assert refused == ["batch_size", "data_dir", "optim.learning_rate", "seed"]
    assert changes["seed"] == (0, 3) and len(changes) == 7
    # A run saved before a key existed resumes: the key is reported, not refused.
    del saved["optim"]["eps"]
    c = detector_configs.get_config("tiny")
    assert run_config.check_resume_config(saved, c, allow_change=False) == (
        {"optim.eps": (None, 1e-8)}, [])


# --------------------------------------------------------------------------- TensorBoard


def _tfrecords(path):
    """The records of a TFRecord file (length u64, its CRC u32, data, data CRC u32)."""
    data = path.read_bytes()
    i = 0
    while i < len(data):
        (n,) = struct.unpack("<Q", data[i:i + 8])
        yield data[i + 12:i + 12 + n]
        i += 12 + n + 4


def tensorboard_scalar_steps(tb_dir) -> dict[str, list[int]]:
    """Scalar steps per tag as TensorBoard shows them.

    TensorBoard's ``EventAccumulator`` reads a run's event files in name order; for files of
    version ``brain.Event:2`` (tensorboardX's) a ``SessionLog.START`` event at step s purges
    every event read so far at step >= s (``_CheckForRestartAndMaybePurge``); otherwise every
    event is kept, duplicates included.
    """
    from tensorboardX.proto.event_pb2 import Event, SessionLog

    steps: dict[str, list[int]] = {}
    for path in sorted(p for p in tb_dir.iterdir() if ".tfevents." in p.name):
        version = 0.0
        for record in _tfrecords(path):
            ev = Event.FromString(record)
            if ev.HasField("file_version"):
                version = float(ev.file_version.split(":")[-1])
            if (version >= 2 and ev.HasField("session_log")
                    and ev.session_log.status == SessionLog.START):
                steps = {tag: [s for s in v if s < ev.step] for tag, v in steps.items()}
            for value in ev.summary.value:
                steps.setdefault(value.tag, []).append(ev.step)
    return steps


def test_resume_logs_each_step_once_and_keeps_the_changed_config(toy, tmp_path):
    """A run that logged step 3 but died before its step-3 checkpoint resumes from 2:
    TensorBoard shows each step once (the tests' 3-step config: its compiled step is shared).
    The resume changes a refused key (refused without the flag, config.json untouched) and a
    free one; with the flag both are recorded."""
    workdir = tmp_path / "run"
    one = jax.devices()[:1]
    cfg = small_config(toy)
    td.train(cfg, workdir, devices=one, step_cache=STEPS)
    run = RunDir(workdir)
    assert run.checkpoint_steps() == [2, 3]
    shutil.rmtree(run.checkpoint_dir / "3")  # died after logging step 3, before saving it
    saved_text = run.config_file.read_text()

    changed = small_config(toy, **{"eval.num_examples": 5, "checkpoint.max_to_keep": 2})
    with pytest.raises(run_config.ConfigError,
                       match=r"eval\.num_examples=6 \(now 5\); .*--allow_config_change"):
        td.DetectorTrainer(changed, workdir, devices=one, step_cache=STEPS)
    assert run.config_file.read_text() == saved_text and run.read_config_history() == []

    resumed = td.DetectorTrainer(changed, workdir, devices=one, step_cache=STEPS,
                                 allow_config_change=True)
    assert resumed.start_step == 2
    resumed.run()
    steps = tensorboard_scalar_steps(run.tb_dir)
    assert "train/loss" in steps and "train/learning_rate" in steps
    for tag, seen in steps.items():
        assert seen == [1, 2, 3], (tag, seen)

    history = run.read_config_history()
    assert len(history) == 1
    entry = history[0]
    assert entry["step"] == 2 and entry["forced"] == ["eval.num_examples"]
    assert entry["changes"] == {"checkpoint.max_to_keep": {"old": 3, "new": 2},
                                "eval.num_examples": {"old": 6, "new": 5}}
    assert entry["previous_config"] == json.loads(saved_text)
    assert run.read_config()["eval"]["num_examples"] == 5


# --------------------------------------------------------------------------- the launcher


def _fake_run(workdir, cfg):
    """A workdir holding a run of ``cfg`` (as ``launch_args(cfg, ...)`` launches it: the
    fixture's SMALL_KEYS are all the keys ``small_config`` sets) with a bare step-5 checkpoint:
    the launcher must refuse before it restores anything."""
    run = RunDir(workdir)
    run.path.mkdir(parents=True)
    run.write_config(cfg.to_json_best_effort(indent=2, sort_keys=True))
    run.write_model_config(run_config.model_config(cfg))
    (run.checkpoint_dir / "5").mkdir(parents=True)
    (run.checkpoint_dir / "5" / "commit_success.txt").write_text("")
    return run


def test_launcher_refuses_bad_input_in_one_line(toy, tmp_path):
    """Exit status 2, one ``error:`` line naming the problem, no traceback, the workdir left
    as it was: out-of-range values, a batch the devices do not divide, a resume changing the
    seed and batch size, a resume with another model variant."""
    cfg = small_config(toy)
    two_devices = {**SUBPROCESS_ENV, "XLA_FLAGS": SUBPROCESS_ENV["XLA_FLAGS"]
                   + " --xla_force_host_platform_device_count=2"}
    changed = _fake_run(tmp_path / "changed", cfg)
    other_model = _fake_run(tmp_path / "other_model", cfg)
    cases = {
        "steps": (tmp_path / "w_steps", cfg, ["--config.total_steps=0"], SUBPROCESS_ENV,
                  ["total_steps=0 (must be an integer >= 1)"]),
        "trainer": (tmp_path / "w_trainer", cfg, ["--config.trainer=segmenter"], SUBPROCESS_ENV,
                    ["unknown trainer 'segmenter'"]),
        "lr": (tmp_path / "w_lr", cfg, ["--config.optim.learning_rate=-0.001"], SUBPROCESS_ENV,
               ["optim.learning_rate=-0.001 (must be a number > 0)"]),
        "divisible": (tmp_path / "w_div", small_config(toy, batch_size=3, **{"mesh.data": -1}),
                      [], two_devices, ["batch_size=3 is not divisible by the 2 devices"]),
        "changed": (changed.path, small_config(toy, batch_size=8), ["--config.seed=1"],
                    SUBPROCESS_ENV,
                    ["in batch_size=4 (now 8), seed=0 (now 1); ", "--allow_config_change"]),
        "variant": (other_model.path, small_config(toy, **{"model.variant": "tiny/16"}), [],
                    SUBPROCESS_ENV,
                    ["this workdir holds a tiny/8 run", "variant='tiny/8' (config: 'tiny/16')"]),
    }
    before = {name: sorted(p.name for p in w.iterdir()) for name, (w, *_) in cases.items()
              if w.exists()}
    config_text = changed.config_file.read_text()
    procs = {name: subprocess.Popen(launch_args(c, work, extra), env=env, cwd=ROOT,
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for name, (work, c, extra, env, _) in cases.items()}
    for name, proc in procs.items():
        _, err = proc.communicate(timeout=180)
        work, _, _, _, expected = cases[name]
        assert proc.returncode == 2, (name, proc.returncode, err[-3000:])
        lines = err.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in err, (name, err[-3000:])
        assert lines[0].startswith("error: "), (name, lines[0])
        for text in expected:
            assert text in lines[0], (name, text, lines[0])
        if name in before:
            assert sorted(p.name for p in work.iterdir()) == before[name], name
        else:
            assert not work.exists(), name
    assert changed.config_file.read_text() == config_text
    assert other_model.read_model_config().variant == "tiny/8"
    assert os.listdir(changed.checkpoint_dir) == ["5"]
