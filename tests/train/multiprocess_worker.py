"""One of several CPU processes of a distributed training run (test_cluster.py starts them).

``python multiprocess_worker.py CONFIG_JSON WORKDIR OUT_NPZ`` with the environment of a
Kubernetes indexed Job (``JAX_COORDINATOR_ADDRESS``, ``JAX_NUM_PROCESSES``,
``JOB_COMPLETION_INDEX``): joins the job as ``train/launch.py`` does
(``sharding.maybe_initialize_distributed``; gloo collectives, one CPU device per process),
trains steps 1 and 2 by hand, saves a checkpoint, builds a second trainer from the workdir (a
restore) and runs it with ``DetectorTrainer.run``.
Process 0 sends itself SIGTERM once step 3 is logged; JAX's preemption service tells both
processes, which save at the step they agree on and return. Writes this process's batches (its
slice of each global batch), the loss of every step and the step saved on SIGTERM to OUT_NPZ.
"""

import json
import os
import signal
import sys

os.environ["JAX_PLATFORMS"] = "cpu"

import jax  # noqa: E402
import ml_collections  # noqa: E402
import numpy as np  # noqa: E402


def main(config_json, workdir, out):
    # CPU devices of different processes talk through gloo (the default has no cross-process
    # collectives).
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.config.update("jax_num_cpu_devices", 1)
    from train import sharding
    from train import trainer_detector as td

    assert sharding.maybe_initialize_distributed("auto")

    with open(config_json) as f:
        config = ml_collections.ConfigDict(json.load(f))
    assert jax.process_count() == int(os.environ["JAX_NUM_PROCESSES"]) == len(jax.devices())
    assert jax.process_index() == int(os.environ["JOB_COMPLETION_INDEX"])
    record = {}
    cache = td.StepCache()  # the restored trainer reuses the first one's compiled step
    first = td.DetectorTrainer(config, workdir, step_cache=cache)
    for step in (1, 2):
        batch = first.next_batch()
        loss = first.train_step(batch)["loss"]
        record[step] = (batch, float(jax.device_get(loss)))
    first.save()
    first.close()
    resumed = td.DetectorTrainer(config, workdir, step_cache=cache)
    assert resumed.start_step == 2, resumed.start_step

    def hook(step, batch, metrics):
        record[step] = ({k: np.copy(v) for k, v in batch.items()}, metrics["loss"])
        if step == 3 and jax.process_index() == 0:
            os.kill(os.getpid(), signal.SIGTERM)

    summary = resumed.run(hooks=[hook])
    preempted = summary["preempted"]
    assert preempted is not None and preempted < config.total_steps, summary
    arrays = {f"step{s}/{k}": np.asarray(v) for s, (b, _) in record.items()
              for k, v in b.items() if k in td.STEP_FIELDS}
    arrays["losses"] = np.array([record[s][1] for s in range(1, preempted + 1)])
    arrays["preempted"] = np.int64(preempted)
    np.savez(out, **arrays)
    jax.distributed.shutdown()


if __name__ == "__main__":
    main(*sys.argv[1:])
