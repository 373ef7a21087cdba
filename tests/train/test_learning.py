"""End to end learning check: rendered scenes -> records -> a short training run that learns.

Procedural meshes are split by hash into training and held-out objects; the detector trains on
path-traced scenes of the former and is evaluated on scenes of the latter. The held-out
instances matched at IoU 0.5 and AP50 (tile diagnostic) are compared with the same model's at
initialisation (whose boxes are each patch's own cell, too small to reach IoU 0.5 with any
object, so neither matches nor AP50), and the training loss must fall. The run is
deterministic for a given machine and compile options. Takes about three minutes on two cores.
"""

import jax
import numpy as np
import pytest

from datagen import generate, pack
from threept_jax.data.banks import load_object_table
from train import trainer_detector as td
from train.configs.detector import get_config
from train.eval_detector import DetectorEvaluator

SCENE = ["--meshes", "procedural:24", "--resolution", "160", "128", "--spp", "2",
         "--max-depth", "3", "--instances", "8", "--distinct", "2", "6", "--val-fraction",
         "0.25", "--quiet"]


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    root = tmp_path_factory.mktemp("learn")
    for split, scenes, per_scene in (("train", 10, 4), ("val", 4, 2)):
        generate.main([*SCENE, "--out", str(root / split), "--split", split,
                       "--num-scenes", str(scenes), "--images-per-scene", str(per_scene)])
        # Banks of meshes decimated to 1024 faces: 5 rasterizer programs instead of 9 (the
        # procedural parts have 20-3456 faces); held-out tile AP50 0.029 and 0.033 at seeds 0
        # and 1 (0.027 at seed 0 with the default 20000; 256 faces gave 0.018).
        pack.main(["--scenes", str(root / split / f"{split}_pbr"), "--out", str(root / "rec"),
                   "--name", split, "--split-label", split, "--bank-size", "32",
                   "--num-templates", "128", "--bank-max-faces", "1024", "--quiet"])
    return root / "rec"


def test_tiny_detector_learns_and_generalises_to_held_out_meshes(records, tmp_path):
    c = get_config("tiny")
    c.data_dir = str(records)
    c.total_steps = 400
    c.batch_size = 16
    c.eval.update(every_steps=0, num_examples=96, batch_size=16, num_templates=-1)
    c.checkpoint.update(every_steps=0, async_save=False)
    c.mesh.update(data=1, fsdp=1)
    c.progress_bar = False
    table = load_object_table(records)
    held_out = {k for k, v in table.items() if v.split == "val"}
    assert held_out and held_out.isdisjoint(k for k, v in table.items() if v.split == "train")

    trainer = td.DetectorTrainer(c, tmp_path / "run", devices=jax.devices()[:1])
    evaluator = DetectorEvaluator(c, trainer.compiled.graphdef, trainer.mesh, trainer.table)
    before = evaluator(trainer.state["params"])
    losses = []
    trainer.run(hooks=[lambda step, batch, m: losses.append(m["loss"])])
    after = evaluator(trainer.state["params"])

    first, last = np.mean(losses[:25]), np.mean(losses[-25:])
    assert last < 0.75 * first, (first, last)
    # Learning shows first where training puts objects (the tile diagnostic; the full-image
    # AP50 of 400 tiny steps is near 0: README, known limits). At initialisation no box
    # reaches IoU 0.5 with a held-out instance (each patch's own cell); after training some are
    # matched one-to-one at IoU 0.5 (22 and 31 of 128 on one machine, in this suite and in a
    # script of the same code). The AP50 of so weak a detector rides on the ranking of its
    # scores and moves twofold with the last bits of the arithmetic (0.009 and 0.020 in those
    # two runs, 0.022-0.040 on other machines), so it must only rise from zero.
    tile = "eval/tile_diagnostic/"
    assert before[tile + "num_matched"] == 0 and after[tile + "num_gt"] > 50, (before, after)
    assert after[tile + "num_matched"] / after[tile + "num_gt"] > 0.06, (before, after)
    assert after[tile + "ap50"] > before[tile + "ap50"] == 0.0, (before, after)
    assert 0.0 <= after["eval/ap50"] <= 1.0 and after["eval/num_images"] > 0
