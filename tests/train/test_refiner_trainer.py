"""3PT-R trainer: configs, single compilation, exact resume, the launcher, the held-out eval."""

import json
import os
import signal
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from fixtures.refiner_records import write_refiner_records
from fixtures.training import ROOT, SUBPROCESS_ENV, apply_overrides

from threept_jax.data.run_dir import RunDir
from threept_jax.models.configs import REFINER_SIZES, RefinerConfig
from train import eval_refiner, run_config
from train import trainer as trainer_lib
from train import trainer_refiner as trr
from train.configs import refiner as refiner_configs
from train.eval_refiner import mesh_digests, training_digests
from train.trainer import StepCache

STEPS = StepCache(maxsize=4)
ONE = jax.devices()[:1]  # tests/conftest.py makes 4 CPU devices; the refiner's runs use one


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    """Train/val folder (3 objects) and a held-out folder of other meshes."""
    root = tmp_path_factory.mktemp("refrec")
    seen = write_refiner_records(root / "seen", num_objects=3, mesh_seed=0, num_images=12,
                                 splits=("train", "val"), max_faces=600)
    held = write_refiner_records(root / "held", num_objects=2, mesh_seed=1, num_images=6,
                                 splits=("val",), max_faces=600)
    return seen, held


def small_config(data_dir, **overrides):
    c = refiner_configs.get_config("tiny")
    c.data_dir = str(data_dir)
    c.total_steps = 4
    c.batch_size = 2
    c.data.update(num_hypotheses=3, max_symmetries=8)
    c.refine.update(num_matches=16, max_faces=256)
    c.optim.warmup_steps = 1
    c.eval.update(every_steps=0, num_examples=5, batch_size=2, num_steps=2)
    c.checkpoint.update(every_steps=2, async_save=False)
    c.mesh.update(data=1, fsdp=1, fsdp_min_size=0)
    c.log_every = 1
    c.progress_bar = False
    return apply_overrides(c, overrides)


def _params(trainer):
    return jax.tree.map(lambda x: np.asarray(jax.device_get(x)), trainer.state["params"])


def test_configs_are_valid_and_each_trainer_refuses_the_others_keys():
    for name in REFINER_SIZES:
        c = refiner_configs.get_config(name)
        run_config.check_config(c)
        cfg = run_config.model_config(c)
        assert isinstance(cfg, RefinerConfig)
        assert cfg.variant == REFINER_SIZES[name]["variant"]
        assert run_config.refiner_example_config(c).crop_size == cfg.crop_size
        run_config.loss_config(c)
        run_config.refine_settings(c)
    with pytest.raises(run_config.ConfigError, match="unknown config key 'data.max_instances'"):
        run_config.check_key("data.max_instances", "refiner")
    with pytest.raises(run_config.ConfigError, match="unknown config key 'refine"):
        run_config.check_key("refine.num_matches", "detector")
    with pytest.raises(ValueError, match="unknown refiner config 'huge'"):
        refiner_configs.get_config("huge")


def test_one_compilation_and_a_resumed_run_ends_where_an_uninterrupted_one_does(records,
                                                                                tmp_path):
    seen, _ = records
    c = small_config(seen)
    straight = trr.RefinerTrainer(c, tmp_path / "straight", step_cache=STEPS, devices=ONE)
    summary = straight.run()
    p_straight = _params(straight)
    assert straight.compiled.trace_counter[0] == 1
    assert np.isfinite(summary["train"]["loss"])
    for k in ("matching/loss", "classification/loss", "segmentation/loss", "mssd_after"):
        assert k in summary["train"], k

    # The same run stopped by SIGTERM (preemption: it saves and returns), then resumed; all
    # three trainers share one compiled step.
    def preempt(step, batch, metrics):
        if step == 1:
            os.kill(os.getpid(), signal.SIGTERM)

    first = trr.RefinerTrainer(c, tmp_path / "resumed", step_cache=STEPS, devices=ONE)
    stopped = first.run(hooks=[preempt])["preempted"]
    assert stopped is not None and 1 <= stopped < c.total_steps
    p_first = _params(first)
    resumed = trr.RefinerTrainer(c, tmp_path / "resumed", step_cache=STEPS, devices=ONE)
    assert resumed.start_step == stopped
    resumed.run()
    assert resumed.compiled is straight.compiled and straight.compiled.trace_counter[0] == 1
    for a, b in zip(jax.tree.leaves(p_straight), jax.tree.leaves(_params(resumed))):
        np.testing.assert_allclose(a, b, rtol=2e-5, atol=2e-6)
    moved = [not np.allclose(a, b) for a, b in
             zip(jax.tree.leaves(p_straight), jax.tree.leaves(p_first))]
    assert any(moved)  # the steps after the preemption changed the parameters
    # The run directory is a refiner's.
    run = RunDir(tmp_path / "resumed", model="refiner")
    assert run.read_model_config() == run_config.model_config(c)
    assert not (tmp_path / "resumed" / "detector.json").exists()


def test_frozen_groups_get_no_gradient_and_no_weight_decay():
    """``optim.freeze``: against the hand-derived gradient of sum((S H)^2), d/dH = 2 S^T S H."""
    s0 = np.arange(9.0, dtype=np.float32).reshape(3, 3) / 9
    h0 = np.eye(3, dtype=np.float32) + 0.5
    params = {"stem": {"w": jnp.asarray(s0)}, "head": {"w": jnp.asarray(h0)}}
    frozen = trainer_lib.frozen_groups(" stem, ")
    assert frozen == {"stem"}

    def loss(p):
        p = trainer_lib.hold_frozen(p, frozen)
        return jnp.sum((p["stem"]["w"] @ p["head"]["w"]) ** 2)

    grads = jax.grad(loss)(params)
    assert not np.any(grads["stem"]["w"])
    np.testing.assert_allclose(grads["head"]["w"], 2 * s0.T @ s0 @ h0, rtol=1e-5)
    tx, _ = trainer_lib.make_optimizer({"freeze": "stem", "weight_decay": 0.5,
                                        "warmup_steps": 0}, total_steps=10)
    updates, _ = tx.update(grads, tx.init(params), params)
    assert not np.any(updates["stem"]["w"]) and np.all(np.abs(updates["head"]["w"]) > 0)
    # A trainer that does not hold them (the detector's): the optimizer alone leaves them.
    plain = jax.grad(lambda p: jnp.sum((p["stem"]["w"] @ p["head"]["w"]) ** 2))(params)
    assert np.all(np.abs(plain["stem"]["w"]) > 0)
    updates, _ = tx.update(plain, tx.init(params), params)
    assert not np.any(updates["stem"]["w"]) and np.all(np.abs(updates["head"]["w"]) > 0)
    # Nothing frozen: the state of before (clipping, AdamW), so older checkpoints resume.
    none, _ = trainer_lib.make_optimizer({"warmup_steps": 0}, total_steps=10)
    assert len(none.init(params)) == 2
    with pytest.raises(ValueError, match=r"optim.freeze names \['steam'\].*\['head', 'stem'\]"):
        trainer_lib.hold_frozen(params, frozenset({"steam"}))
    typo, _ = trainer_lib.make_optimizer({"freeze": "steam"}, total_steps=10)
    with pytest.raises(ValueError, match=r"optim.freeze names \['steam'\]"):
        typo.init(params)  # any trainer's optimizer refuses it too


def test_a_refiner_run_refuses_a_detector_workdir(records, tmp_path):
    seen, _ = records
    (tmp_path / "detector.json").write_text(json.dumps({"variant": "tiny/16"}))
    (tmp_path / "checkpoints" / "2" / "state").mkdir(parents=True)
    with pytest.raises(ValueError, match="holds a detector run"):
        trr.RefinerTrainer(small_config(seen), tmp_path, step_cache=STEPS, devices=ONE)


def test_evaluation_on_held_out_meshes_says_they_are_unseen(records, tmp_path, capsys):
    """Through the evaluation command on a run directory, as a user runs it. (A run with XFeat
    as its pretrained stem: tests/scripts/test_device.py, whose dry run trains one frozen,
    finds its stem equal to the converted weights to the bit, fine-tunes it and loads it for
    inference; tests/models/test_xfeat.py checks those weights against the upstream network's
    outputs, tests/models/test_refiner.py the stem's projection starting at zero.)"""
    seen, held = records
    c = small_config(seen, **{"eval.data_dir": str(held)})
    trainer = trr.RefinerTrainer(c, tmp_path / "w", step_cache=STEPS, devices=ONE)
    trainer.save()  # the initial weights, as step 0
    trainer.close()
    assert eval_refiner.main(["--workdir", str(tmp_path / "w"), "--step", "latest",
                              "--split", "val", "--num-examples", "5"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["step"] == 0
    assert out["eval/unseen_share"] == 1.0
    assert out["eval/num_instances"] > 0
    for k in ("eval/match_within_2px", "eval/ar_mssd_before", "eval/ar_mssd_after_1",
              "eval/ar_mssd_after_2", "eval/score_acc", "eval/mask_iou"):
        assert 0.0 <= out[k] <= 1.0, k
    assert out["eval/ar_mssd_after"] == out["eval/ar_mssd_after_2"]
    # The val split of the training folder shows the training meshes: not held out.
    assert set(mesh_digests(seen).values()) <= training_digests(seen)
    assert not set(mesh_digests(held).values()) & training_digests(seen)
    with pytest.raises(SystemExit) as e:  # not a run: the usage error, exit 2
        eval_refiner.main(["--workdir", str(tmp_path)])
    assert e.value.code == 2


def test_launcher_refuses_a_detector_key_in_a_refiner_config(tmp_path):
    """(The launcher training the refiner, and what it wrote loaded, inferred with and evaluated:
    tests/scripts/test_device.py, whose dry run trains through the launcher.)"""
    base = [sys.executable, str(ROOT / "train" / "launch.py"), "--config",
            str(ROOT / "train" / "configs" / "refiner.py") + ":tiny"]
    bad = subprocess.run(base + ["--workdir", str(tmp_path / "bad"), "--config.data.max_instances=3"],
                         env=SUBPROCESS_ENV, capture_output=True, text=True, timeout=120)
    lines = [ln for ln in bad.stderr.splitlines() if ln.strip()]
    assert bad.returncode == 2 and "Traceback" not in bad.stderr, bad.stderr[-3000:]
    assert lines[-1].startswith("error: unknown config key 'data.max_instances'")
    assert "num_hypotheses" in lines[-1]  # the refiner's data keys are listed
