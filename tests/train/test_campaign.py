"""``python -m train.campaign``: a toy campaign run, stopped, resumed and refused other data."""

import json
import signal

import pytest

from threept_jax.data.run_dir import RunDir
from train import campaign

#: Measured warm step time stands in for the throw-away probe (its own test: test_adapt).
STEP_SECONDS = 0.5
TOY = ["--parts", "6", "--heldout", "0.5", "--train-images", "4", "--heldout-images", "2",
       "--resolution", "96", "80", "--spp", "1", "--instances", "3", "--seed", "1"]


def test_bad_arguments_exit_2_naming_the_flag(tmp_path, capsys):
    for argv, match in (
        (["--hours", "0"], "--hours must be in"),
        (["--parts", "1"], "--parts must be >= 2"),
        (["--heldout", "1"], "--heldout must be a share in (0, 1)"),
        (["--train-images", "1"], "--train-images must be >= 2"),
        (["--resolution", "32", "32"], "--resolution must be at least"),
    ):
        with pytest.raises(SystemExit) as e:
            campaign.main(["--model", "detector", "--hours", "1", "--workdir",
                           str(tmp_path / "w"), *argv])
        assert e.value.code == 2
        assert match in capsys.readouterr().err
    assert not (tmp_path / "w").exists()


def test_share_splits_a_total():
    assert [campaign.share(7, i, 3) for i in range(3)] == [3, 2, 2]
    assert sum(campaign.share(1500, i, 2) for i in range(2)) == 1500


def test_campaign_holds_parts_out_trains_resumes_and_keeps_its_data(tmp_path, monkeypatch):
    monkeypatch.setattr(campaign.stages, "measure_step_seconds", lambda config: STEP_SECONDS)
    monkeypatch.setattr(campaign, "NUM_EVALS", 1)  # one held-out evaluation (at the end), not eight
    w = tmp_path / "w"
    hours = 0.002  # 7.2 s: int(7.2 * 0.85 / 0.5) = 12 steps
    argv = ["--model", "detector", "--hours", str(hours), "--workdir", str(w), *TOY]

    # Stopped by SIGTERM after its first checkpointed step: the trainer saves and returns.
    from train import trainer as trainer_module

    real_run = trainer_module.Trainer.run

    def run_then_stop(self, *a, **k):
        steps = []
        real_step = self.train_step

        def step(batch):
            steps.append(1)
            if len(steps) == 3:
                signal.raise_signal(signal.SIGTERM)
            return real_step(batch)

        self.train_step = step
        return real_run(self, *a, **k)

    monkeypatch.setattr(trainer_module.Trainer, "run", run_then_stop)
    plan = campaign.main(argv)
    steps = plan["detector"]["steps"]
    assert steps == int(hours * 3600 * (1 - campaign.stages.EVAL_SHARE) / STEP_SECONDS) == 12
    run = RunDir(w / "detector")
    stopped = run.checkpoint_steps()[-1]
    assert 0 < stopped < steps

    # The held-out parts never appear in the training records, and only they are in val.
    by_id = {int(k): v for k, v in
             json.loads((w / "records" / "objects.json").read_text()).items()}
    index = {name: json.loads((w / "records" / name / "index.json").read_text())
             for name in ("train", "val")}
    used = {name: {int(v) for src in index[name]["sources"] for v in src["obj_ids"].values()}
            for name in index}
    assert used["train"] and used["val"] and not used["train"] & used["val"]
    assert {by_id[i]["split"] for i in used["val"]} == {"val"}
    assert {by_id[i]["split"] for i in used["train"]} == {"train"}
    layouts = {src["scenes"].split("/")[-2] for src in index["train"]["sources"]}
    assert layouts == set(campaign.LAYOUTS)

    # Exported with its training state (the run is unfinished), checksummed.
    from train import export

    model = tmp_path / "models" / "detector-toy"
    model.mkdir(parents=True)
    (model / "MODEL_CARD.md").write_text("card")
    info = export.main(["--run", str(w / "detector"), "--out", str(model),
                        "--campaign", str(w / "campaign.json")])
    assert info["resumable"] and info["latest"] == stopped
    assert (model / "MODEL_CARD.md").read_text() == "card"
    assert (model / "checkpoints" / str(stopped) / "data").is_dir()
    RunDir(model).verify()

    # Resumed on "another machine": a fresh workdir started from the exported model regenerates
    # the same images, keeps the plan (not measured again) and trains from the stopped step.
    monkeypatch.setattr(trainer_module.Trainer, "run", real_run)
    monkeypatch.setattr(campaign.stages, "measure_step_seconds",
                        lambda config: pytest.fail("a resumed campaign measured again"))
    w2 = tmp_path / "w2"
    argv2 = [*argv[:4], "--workdir", str(w2), *TOY, "--resume-from", str(model)]
    plan = campaign.main(argv2)
    run2 = RunDir(w2 / "detector")
    assert run2.checkpoint_steps()[-1] == steps
    assert plan["detector"]["steps"] == steps
    assert [s["model"] for s in plan["sessions"]] == ["detector", "detector"]
    first = sorted((w / "data").rglob("rgb/*"))
    assert first and [p.read_bytes() for p in first] == [
        (w2 / p.relative_to(w)).read_bytes() for p in first]

    # Run again when finished: nothing is remade.
    images = sorted(p.stat().st_mtime for p in (w2 / "data").rglob("rgb/*"))
    campaign.main(argv2)
    assert sorted(p.stat().st_mtime for p in (w2 / "data").rglob("rgb/*")) == images

    # Finished: exported without training state, and refused as a start.
    info = export.main(["--run", str(w2 / "detector"), "--out", str(model),
                        "--campaign", str(w2 / "campaign.json")])
    assert not info["resumable"]
    assert not list((model / "checkpoints").rglob("data"))
    with pytest.raises(SystemExit, match="finished model"):
        campaign.main([*argv[:4], "--workdir", str(tmp_path / "w3"), *TOY, "--resume-from", str(model)])

    # Other data settings would change the images: refused, naming the saved value.
    with pytest.raises(SystemExit, match=r"--parts 6 \(given 7\)"):
        campaign.main([*argv, "--parts", "7"])
