"""3PT-D trainer: sharded step equivalence, single compilation, kill-and-resume, checks, eval."""

import json
import signal
import subprocess
import time

import jax
import numpy as np
import pytest
from fixtures.training import ROOT, STEPS, SUBPROCESS_ENV, launch_args, small_config
from flax import nnx

from infer.checkpoint import load_detector
from threept_jax.data.run_dir import RunDir
from threept_jax.models.detector import Detector
from threept_jax.models.vit import count_params
from train import eval_detector, run_config, sharding
from train import trainer_detector as td
from train.configs import detector as detector_configs


def _params_np(trainer):
    return jax.tree.map(lambda x: np.asarray(jax.device_get(x)), trainer.state["params"])


def test_configs_have_the_required_keys_and_valid_models():
    for name in ("tiny", "cpu", "small", "paper"):
        c = detector_configs.get_config(name)
        for key in ("total_steps", "batch_size", "data_dir", "seed"):
            assert key in c, (name, key)
        run_config.check_config(c)
        cfg = run_config.model_config(c)
        run_config.loss_config(c)
        assert cfg.image_size == c.model.image_size
    paper = run_config.model_config(detector_configs.get_config("paper"))
    n = count_params(nnx.eval_shape(lambda: Detector(paper, rngs=nnx.Rngs(0))))
    # B/16 backbone at 512 px (85.0M blocks + 0.6M patch + 0.8M position embedding), two
    # attention pools (7.1M each) and five 768x768 projections/head layers (3M): ~104M.
    assert 102e6 < n < 106e6
    with pytest.raises(ValueError, match="tiny, cpu, small or paper"):
        detector_configs.get_config("huge")


def test_param_sharding_rule():
    assert sharding.param_spec((64, 256), 2, 0) == jax.sharding.PartitionSpec(None, "fsdp")
    assert sharding.param_spec((6, 3), 2, 0) == jax.sharding.PartitionSpec("fsdp", None)
    assert sharding.param_spec((3, 5), 2, 0) == jax.sharding.PartitionSpec()
    assert sharding.param_spec((64, 256), 2, 10**6) == jax.sharding.PartitionSpec()
    assert sharding.param_spec((), 4, 0) == jax.sharding.PartitionSpec()
    assert sharding.mesh_shape(-1, 2, 8) == (4, 2)
    with pytest.raises(ValueError, match="product"):
        sharding.mesh_shape(3, 1, 4)


def test_one_device_and_four_devices_agree_and_compile_once(toy, tmp_path):
    assert len(jax.devices()) >= 4, "tests/conftest.py sets jax_num_cpu_devices=4"
    one = td.DetectorTrainer(small_config(toy), tmp_path / "one", devices=jax.devices()[:1],
                             step_cache=STEPS)
    four = td.DetectorTrainer(small_config(toy, **{"mesh.data": 2, "mesh.fsdp": 2}),
                              tmp_path / "four", devices=jax.devices()[:4], step_cache=STEPS)
    specs = {s.spec for s in jax.tree.leaves(four.compiled.state_shardings)}
    assert any("fsdp" in tuple(s) for s in specs)  # parameters really are sharded
    kernel = four.state["params"]["image_tower"]["blocks"][0]["mlp"]["fc1"]["kernel"]
    assert len({d for d in kernel.sharding.device_set}) == 4
    assert kernel.addressable_shards[0].data.shape != kernel.shape
    np.testing.assert_array_equal(jax.tree.leaves(_params_np(one))[0],
                                  jax.tree.leaves(_params_np(four))[0])
    c1, c4 = one.compiled.trace_counter[0], four.compiled.trace_counter[0]
    for _ in range(2):
        batch = one.next_batch()
        m1 = jax.device_get(one.train_step(batch))
        m4 = jax.device_get(four.train_step(batch))
        assert np.isfinite(m1["loss"]) and m1["num_boxes"] > 0
        for k in ("loss", "loss_presence", "loss_l1", "loss_giou", "loss_orientation",
                  "grad_norm"):
            np.testing.assert_allclose(m4[k], m1[k], rtol=1e-5, atol=1e-6, err_msg=k)
    # Attention key biases shift all logits of a query equally, so softmax gives them an
    # exactly zero gradient; Adam's normalisation turns the rounding noise of that zero into
    # +-lr steps whose sign depends on the summation order. Every other parameter must agree.
    flat1 = jax.tree_util.tree_flatten_with_path(_params_np(one))[0]
    flat4 = jax.tree.leaves(_params_np(four))
    compared = 0
    for (path, a), b in zip(flat1, flat4, strict=True):
        name = jax.tree_util.keystr(path)
        if "['key']['bias']" in name:
            continue
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-5, err_msg=name)
        compared += 1
    assert compared > 70
    # Evaluation on the 2 x 2 mesh (sharded batch, FSDP parameters) sees the same detections.
    r1, r4 = one.evaluator.detections(one.state["params"]), four.evaluator.detections(
        four.state["params"])
    assert r1["gt_valid"].sum() == 6 and r1["det_valid"].any()
    for k in ("det_scores", "det_boxes", "gt_boxes"):
        np.testing.assert_allclose(r4[k], r1[k], rtol=1e-4, atol=1e-4, err_msg=k)
    for k in ("det_valid", "gt_mask", "gt_obj_index"):
        np.testing.assert_array_equal(r4[k], r1[k], err_msg=k)
    # And the full-image detections (pan-and-scan over all val objects).
    i1, i4 = (t.evaluator.image_detections(t.state["params"]) for t in (one, four))
    assert len(i1) == 6 and any(o["product"]["valid"].any() for o in i1)
    for a, b in zip(i1, i4, strict=True):
        for mode in a:
            np.testing.assert_allclose(b[mode]["scores"], a[mode]["scores"], rtol=1e-4,
                                       atol=1e-6, err_msg=mode)
            np.testing.assert_allclose(b[mode]["boxes"], a[mode]["boxes"], atol=1e-3,
                                       err_msg=mode)
    # The parameters moved, and each step function was traced (compiled) once for two steps.
    assert one.step == 2 and four.step == 2
    assert one.compiled.trace_counter[0] - c1 <= 1 and four.compiled.trace_counter[0] - c4 <= 1
    assert one.compiled.trace_counter[0] >= 1 and four.compiled.trace_counter[0] >= 1
    one.close()
    four.close()


def _record(log):
    def hook(step, batch, metrics):
        log[step] = ({k: np.copy(v) for k, v in batch.items()}, metrics["loss"])
    return hook


def _assert_same_batch(a, b):
    assert set(a) == set(b)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_kill_and_resume_in_process(toy, tmp_path, monkeypatch):
    cfg = small_config(toy, **{"eval.every_steps": 3})
    full = {}
    summary = td.train(cfg, tmp_path / "full", hooks=[_record(full)], devices=jax.devices()[:1],
                       step_cache=STEPS)
    assert sorted(full) == [1, 2, 3]
    ev = summary["eval"]
    assert 0.0 <= ev["eval/ap50"] <= 1.0 and ev["eval/num_images"] == 6 and ev["eval/num_gt"] > 0
    assert 0.0 <= ev["eval/tile_diagnostic/orientation_acc"] <= 1.0
    assert ev["eval/tile_diagnostic/num_gt"] > 0
    assert (tmp_path / "full" / "tb").is_dir() and any((tmp_path / "full" / "tb").iterdir())
    # Interrupted run: two steps, a checkpoint, then the process "dies".
    first = td.DetectorTrainer(cfg, tmp_path / "cut", devices=jax.devices()[:1],
                               step_cache=STEPS)
    for step in (1, 2):
        batch = first.next_batch()
        _assert_same_batch(batch, full[step][0])
        assert float(first.train_step(batch)["loss"]) == pytest.approx(full[step][1], rel=1e-6)
    first.save()
    first.close()
    del first
    resumed_log = {}
    again = td.DetectorTrainer(cfg, tmp_path / "cut", devices=jax.devices()[:1],
                               step_cache=STEPS)
    assert again.start_step == 2 and again.step == 2
    again.run(hooks=[_record(resumed_log)])
    assert sorted(resumed_log) == [3]
    _assert_same_batch(resumed_log[3][0], full[3][0])
    assert resumed_log[3][1] == pytest.approx(full[3][1], rel=1e-6)
    # Inference loads exactly the trained parameters (and the model config) from the workdir.
    model, model_cfg, step = load_detector(tmp_path / "cut", step="latest")
    assert step == 3 and model_cfg == run_config.model_config(cfg)
    loaded = nnx.to_pure_dict(nnx.state(model, nnx.Param))
    jax.tree.map(np.testing.assert_array_equal, loaded, _params_np(again))
    # A relative workdir works too (Orbax itself refuses relative paths).
    monkeypatch.chdir(tmp_path)
    assert load_detector("cut", step="best")[2] == 3


def test_best_checkpoint_survives_a_restart(tmp_path):
    from infer.checkpoint import saved_metrics
    from train.checkpointing import Checkpointer

    (tmp_path / "config.json").write_text(json.dumps(
        {"checkpoint": {"best_metric": "eval/ap50", "best_mode": "max"}}))
    ckpt = Checkpointer(tmp_path, max_to_keep=1, async_save=False)
    state = {"w": np.zeros(3, np.float32)}
    for step, ap50 in ((1, 0.2), (2, 0.7), (3, None), (4, 0.4)):
        ckpt.save(step, state, None, None if ap50 is None else {"eval/ap50": ap50, "eval/ap": 0.1})
    ckpt.manager.close()
    # Kept: the latest (4) and the best (2); read back by a fresh process's loader.
    steps = sorted(int(p.name) for p in (tmp_path / "checkpoints").iterdir() if p.name.isdigit())
    assert steps == [2, 4]
    assert RunDir(tmp_path).best_step() == 2 and RunDir(tmp_path).checkpoint_steps() == steps
    assert saved_metrics(tmp_path, 2) == {"eval/ap50": 0.7, "eval/ap": 0.1}


def test_best_checkpoint_is_chosen_by_the_full_image_ap50(toy, tmp_path, monkeypatch):
    """Scripted metrics, one evaluation per step: the full-image AP50 peaks at step 2, the tile
    diagnostic at step 1; the run keeps and picks step 2."""
    image_ap50 = iter([0.2, 0.8, 0.5])
    tile_ap50 = iter([0.9, 0.1, 0.5])
    monkeypatch.setattr(eval_detector, "full_image_metrics",
                        lambda *a, **k: {"eval/ap50": next(image_ap50)})
    monkeypatch.setattr(eval_detector, "compute_metrics",
                        lambda *a, **k: {"eval/tile_diagnostic/ap50": next(tile_ap50)})
    cfg = small_config(toy, **{"eval.every_steps": 1, "checkpoint.every_steps": 1,
                               "checkpoint.max_to_keep": 1})
    assert cfg.checkpoint.best_metric == "eval/ap50"  # the default
    with pytest.warns(UserWarning, match="no 6D AP"):  # the toy objects have no meshes
        td.train(cfg, tmp_path, devices=jax.devices()[:1], step_cache=STEPS)
    assert RunDir(tmp_path).best_step() == 2


def test_every_evaluation_is_saved_with_its_checkpoint(toy, tmp_path, monkeypatch):
    """Evaluations every step, checkpoints every 2, 3 steps (the module's config, so its
    compiled step is the first test's): an evaluation's step (1, neither a checkpoint step nor
    the last) gets a checkpoint holding its metrics, so it can be ranked; by hand the saves are
    1, 2, 3."""
    from infer.checkpoint import saved_metrics

    scores = iter([0.3, 0.6, 0.5])
    monkeypatch.setattr(eval_detector, "full_image_metrics",
                        lambda *a, **k: {"eval/ap50": next(scores)})
    monkeypatch.setattr(eval_detector, "compute_metrics", lambda *a, **k: {})
    cfg = small_config(toy, **{"eval.every_steps": 1, "checkpoint.every_steps": 2,
                               "checkpoint.max_to_keep": 10})
    with pytest.warns(UserWarning, match="no 6D AP"):
        td.train(cfg, tmp_path, devices=jax.devices()[:1], step_cache=STEPS)
    run = RunDir(tmp_path)
    assert run.checkpoint_steps() == [1, 2, 3]
    assert saved_metrics(tmp_path, 1)["eval/ap50"] == 0.3
    assert saved_metrics(tmp_path, 3)["eval/ap50"] == 0.5
    assert run.best_step() == 2


def test_killed_subprocess_resumes_to_the_same_batch(toy, tmp_path):
    """A real run killed with SIGKILL after its step-2 checkpoint resumes to step 3 exactly."""
    workdir = tmp_path / "killed"
    cfg = small_config(toy, total_steps=1000)
    args = launch_args(cfg, workdir)
    proc = subprocess.Popen(args, env=SUBPROCESS_ENV, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, cwd=ROOT)
    try:
        deadline = time.time() + 240
        while not (workdir / "checkpoints" / "2" / "commit_success.txt").exists():
            if proc.poll() is not None:
                raise AssertionError(f"training process exited early: {proc.stderr.read()[-3000:]}")
            assert time.time() < deadline, "no step-2 checkpoint within 4 minutes"
            time.sleep(0.2)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    steps = sorted(int(p.name) for p in (workdir / "checkpoints").iterdir() if p.name.isdigit())
    assert steps and steps[-1] >= 2
    k = steps[-1]
    # Reference: an uninterrupted in-process run over the same config to step k + 1.
    ref_cfg = small_config(toy, total_steps=1000)
    ref = td.DetectorTrainer(ref_cfg, tmp_path / "ref", devices=jax.devices()[:1],
                             step_cache=STEPS)
    for _ in range(k):
        ref.train_step(ref.next_batch())
    ref_batch = ref.next_batch()
    ref_loss = float(ref.train_step(ref_batch)["loss"])
    ref.close()
    resumed = td.DetectorTrainer(ref_cfg, workdir, devices=jax.devices()[:1],
                                 step_cache=STEPS)
    assert resumed.start_step == k
    batch = resumed.next_batch()
    _assert_same_batch(batch, ref_batch)
    assert float(resumed.train_step(batch)["loss"]) == pytest.approx(ref_loss, rel=1e-5)
    resumed.close()


def test_non_finite_loss_stops_with_a_clear_message(toy, tmp_path, monkeypatch):
    trainer = td.DetectorTrainer(small_config(toy), tmp_path / "nan", devices=jax.devices()[:1],
                                 step_cache=STEPS)
    real_next = trainer.next_batch

    def poisoned():
        batch = dict(real_next())
        boxes = batch["boxes"].copy()
        boxes[:] = np.nan
        batch["boxes"], batch["mask"] = boxes, np.ones_like(batch["mask"])
        return batch

    monkeypatch.setattr(trainer, "next_batch", poisoned)
    with pytest.raises(FloatingPointError, match=r"step 1: .*loss=nan.*learning_rate"):
        trainer.run()
    assert not (tmp_path / "nan" / "checkpoints" / "2").exists()  # the bad state is not saved


def test_bad_data_dirs_name_the_fix(toy, tmp_path):
    one = jax.devices()[:1]
    with pytest.raises(ValueError, match="data_dir is empty"):
        td.DetectorTrainer(small_config(""), tmp_path / "w", devices=one, step_cache=STEPS)
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "objects.json").write_text((toy / "objects.json").read_text())
    with pytest.raises(FileNotFoundError, match="datagen.generate"):
        td.DetectorTrainer(small_config(empty), tmp_path / "w", devices=one, step_cache=STEPS)
    with pytest.raises(ValueError, match="num_train_templates"):
        td.DetectorTrainer(small_config(toy, **{"data.num_train_templates": 30}), tmp_path / "w",
                           devices=one, step_cache=STEPS)
    # An object table that misses an object the records use.
    partial = tmp_path / "partial"
    partial.mkdir()
    for split in ("train", "val"):
        (partial / split).symlink_to(toy / split)
    table = json.loads((toy / "objects.json").read_text())
    table = {k: {**v, "bank": str(toy / v["bank"])} for k, v in table.items()
             if v.get("split") == "val"}
    (partial / "objects.json").write_text(json.dumps(table))
    with pytest.raises(KeyError, match="datagen.pack"):
        td.DetectorTrainer(small_config(partial), tmp_path / "w", devices=one, step_cache=STEPS)
    with pytest.raises(ValueError, match="divisible"):
        td.DetectorTrainer(small_config(toy, batch_size=6, **{"mesh.data": 4}), tmp_path / "w",
                           devices=jax.devices()[:4], step_cache=STEPS)


def test_metrics_on_a_hand_made_case():
    """Two tiles of object 5 (1 GT each) and one negative tile of object 9.

    Tile 0: a perfect box, top template 10 degrees off (correct). Tile 1: a perfect box whose
    template is 40 degrees off but matches a 180-degree symmetry of the GT to within 5 degrees
    (correct only up to symmetry) and a low-score false positive. Tile 2: a false positive on
    a negative query. Hand-derived: AP50 = AP = 1 for object 5 (both GT found before any
    false positive), 0 for object 9 (no GT: undefined, excluded by COCO); so AP = 1.
    Orientation: 2 matched, both correct -> 1.0; with the symmetry ignored it would be 0.5.
    """
    from scipy.spatial.transform import Rotation

    rz = lambda deg: Rotation.from_euler("z", deg, degrees=True).as_matrix()  # noqa: E731
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])  # 180 degrees about z
    templates = np.stack([rz(0), rz(10), rz(185), rz(90)])
    boxes = np.zeros((3, 2, 4))
    boxes[0, 0] = [10, 10, 40, 50]
    boxes[1, 0] = [5, 20, 30, 44]
    res = {
        "det_boxes": np.stack([boxes[0], [boxes[1, 0], [40, 40, 60, 60]],
                               [[1, 1, 20, 20], [0, 0, 0, 0]]]),
        "det_scores": np.array([[0.9, 0.0], [0.8, 0.1], [0.7, 0.0]]),
        "det_valid": np.array([[True, False], [True, True], [True, False]]),
        "det_template": np.array([[1, 0], [2, 3], [0, 0]]),
        "gt_boxes": boxes,
        "gt_mask": np.array([[True, False], [True, False], [False, False]]),
        "gt_ignore": np.zeros((3, 2), bool),
        "gt_rotations": np.stack([np.stack([rz(0), np.eye(3)])] * 3),
        "gt_obj_index": np.array([0, 0, 1]),
        "gt_valid": np.array([True, True, True]),
    }
    kw = dict(obj_ids=np.array([5, 9]), template_rotations={5: templates, 9: templates},
              tile=64, threshold_deg=15.0, match_iou=0.5)
    m = eval_detector.compute_metrics(res, symmetries={5: np.stack([np.eye(4), flip]),
                                                       9: np.eye(4)[None]}, **kw)
    m = {k.removeprefix("eval/tile_diagnostic/"): v for k, v in m.items()}
    assert m["ap50"] == pytest.approx(1.0) and m["ap"] == pytest.approx(1.0)
    assert m["num_gt"] == 2 and m["num_matched"] == 2
    assert m["orientation_acc"] == pytest.approx(1.0)
    assert m["orientation_oracle"] == pytest.approx(1.0)
    m = eval_detector.compute_metrics(res, symmetries={5: np.eye(4)[None], 9: np.eye(4)[None]},
                                      **kw)
    assert m["eval/tile_diagnostic/orientation_acc"] == pytest.approx(0.5)


def test_init_from_starts_a_fresh_run_with_the_source_runs_best_parameters(toy, tmp_path):
    """``init_from``: step 0 of the new run holds exactly the parameters the source run had at
    its best checkpoint (scripted here: the last one), the optimizer starts fresh, and a run of
    another model is refused naming the fix."""
    # The module's config (3 steps): its compiled step is the one the first test built.
    source = small_config(toy, **{"checkpoint.every_steps": 3})
    trainer = td.DetectorTrainer(source, tmp_path / "source", devices=jax.devices()[:1],
                                 step_cache=STEPS)
    trainer.run()
    trained = _params_np(trainer)
    assert RunDir(tmp_path / "source").best_step() == 3
    fresh = small_config(toy, init_from=str(tmp_path / "source"), seed=5)
    tuned = td.DetectorTrainer(fresh, tmp_path / "tuned", devices=jax.devices()[:1],
                               step_cache=STEPS)
    assert tuned.start_step == 0 and tuned.step == 0
    jax.tree.map(np.testing.assert_array_equal, _params_np(tuned), trained)
    scratch = td.DetectorTrainer(small_config(toy, seed=5), tmp_path / "scratch",
                                 devices=jax.devices()[:1], step_cache=STEPS)
    same = jax.tree.map(np.array_equal, _params_np(scratch), trained)
    assert not all(jax.tree.leaves(same))  # the check above can tell the two apart
    # The optimizer starts fresh: AdamW's moments and every count at zero, in the layout of a
    # run from scratch (a checkpoint of either restores into the other).
    assert jax.tree.structure(tuned.state["opt_state"]) == jax.tree.structure(
        scratch.state["opt_state"])
    assert all(not np.any(np.asarray(x)) for x in jax.tree.leaves(tuned.state["opt_state"]))
    assert int(tuned.state["step"]) == 0
    tuned.close()
    scratch.close()
    other = small_config(toy, init_from=str(tmp_path / "source"), **{"model.variant": "tiny/16"})
    with pytest.raises(ValueError, match="Fine-tuning keeps the model"):
        td.DetectorTrainer(other, tmp_path / "other", devices=jax.devices()[:1], step_cache=STEPS)
    with pytest.raises(FileNotFoundError, match="not a training run"):
        td.DetectorTrainer(small_config(toy, init_from=str(tmp_path / "nothing")),
                           tmp_path / "none", devices=jax.devices()[:1], step_cache=STEPS)
