"""Device mesh ("data", "fsdp"), parameter and batch shardings, multi-host start-up.

* The mesh is built from ``jax.devices()`` with ``jax.make_mesh`` (both axes ``AxisType.Auto``:
  the code is written for XLA's sharding propagation, not explicit sharding).
* A batch is sharded on its leading axis over both mesh axes (pure data parallelism, with FSDP
  ranks also splitting the batch, as MaxText does).
* A parameter (and its optimizer moments, which have its shape) is sharded over "fsdp" on its
  largest axis divisible by the fsdp size when it has at least ``min_size`` elements, and
  replicated otherwise. XLA gathers sharded weights for the matmuls and reduce-scatters their
  gradients.
* Each process feeds its own slice of the global batch
  (``jax.make_array_from_process_local_data``).
"""

from __future__ import annotations

import os
from typing import Any

import jax
import numpy as np
from jax.sharding import AxisType, Mesh, NamedSharding, PartitionSpec

BATCH_AXES = ("data", "fsdp")


def maybe_initialize_distributed(mode: Any = "auto") -> bool:
    """Call ``jax.distributed.initialize()`` when launched on several hosts.

    ``mode`` True/False (or the strings ``"true"``/``"false"``, as ``--config.distributed=True``
    gives them) forces it; ``"auto"`` initialises when the environment names a coordinator
    (``JAX_COORDINATOR_ADDRESS``) or a multi-task SLURM / Open MPI job, the launchers
    ``jax.distributed.initialize()`` detects by itself (Cloud TPU pods need
    ``--config.distributed=True``). Where JAX detects nothing (a Kubernetes indexed Job without
    the ``kubernetes`` package), ``JAX_COORDINATOR_ADDRESS`` (host:port of process 0),
    ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID`` (default: ``JOB_COMPLETION_INDEX``, which an
    indexed Job sets) name the job. Returns whether it initialised.
    """
    if isinstance(mode, str) and mode.lower() in ("true", "false"):
        mode = mode.lower() == "true"
    if isinstance(mode, str):
        if mode != "auto":
            raise ValueError(f"distributed must be 'auto', True or False, got {mode!r}")
        env = os.environ
        mode = bool(env.get("JAX_COORDINATOR_ADDRESS")) or any(
            int(env.get(k, "1") or 1) > 1 for k in ("SLURM_NTASKS", "OMPI_COMM_WORLD_SIZE"))
    if mode:
        env = os.environ
        kwargs = {}
        if env.get("JAX_NUM_PROCESSES"):
            kwargs["num_processes"] = int(env["JAX_NUM_PROCESSES"])
            process_id = env.get("JAX_PROCESS_ID") or env.get("JOB_COMPLETION_INDEX")
            if process_id is None:
                raise ValueError("JAX_NUM_PROCESSES is set but neither JAX_PROCESS_ID nor "
                                 "JOB_COMPLETION_INDEX is: set JAX_PROCESS_ID to this process's "
                                 "index (0 on the coordinator)")
            kwargs["process_id"] = int(process_id)
        jax.distributed.initialize(**kwargs)
    return bool(mode)


def mesh_shape(data: int, fsdp: int, num_devices: int) -> tuple[int, int]:
    """Resolve -1 entries of (data, fsdp) so that data * fsdp == num_devices."""
    if data == -1 and fsdp == -1:
        raise ValueError("at most one of mesh.data and mesh.fsdp may be -1")
    if fsdp == -1:
        fsdp = num_devices // max(data, 1)
    if data == -1:
        data = num_devices // max(fsdp, 1)
    if data < 1 or fsdp < 1 or data * fsdp != num_devices:
        raise ValueError(
            f"mesh data={data} x fsdp={fsdp} does not use the {num_devices} devices; set "
            f"--config.mesh.data and --config.mesh.fsdp so that their product is {num_devices} "
            "(-1 fills in the rest)")
    return data, fsdp


def make_mesh(data: int = -1, fsdp: int = 1, devices=None) -> Mesh:
    """Mesh with axes ("data", "fsdp") over ``devices`` (default: all of ``jax.devices()``)."""
    devices = jax.devices() if devices is None else list(devices)
    shape = mesh_shape(data, fsdp, len(devices))
    return jax.make_mesh(shape, BATCH_AXES, axis_types=(AxisType.Auto,) * 2, devices=devices)


def param_spec(shape: tuple[int, ...], fsdp: int, min_size: int) -> PartitionSpec:
    """PartitionSpec of one parameter: "fsdp" on its largest axis divisible by ``fsdp``."""
    if fsdp <= 1 or not shape or int(np.prod(shape)) < min_size:
        return PartitionSpec()
    best = None
    for axis, n in enumerate(shape):
        if n % fsdp == 0 and (best is None or n > shape[best]):
            best = axis
    if best is None:
        return PartitionSpec()
    spec = [None] * len(shape)
    spec[best] = "fsdp"
    return PartitionSpec(*spec)


def tree_shardings(tree: Any, mesh: Mesh, min_size: int) -> Any:
    """NamedSharding for every array leaf of ``tree`` (arrays or ShapeDtypeStructs), by shape.

    Because the rule depends only on the shape, optimizer moments get their parameter's
    sharding and scalars (step counters) are replicated.
    """
    fsdp = mesh.shape["fsdp"]
    return jax.tree.map(
        lambda x: NamedSharding(mesh, param_spec(tuple(x.shape), fsdp, min_size)), tree)


def batch_sharding(mesh: Mesh) -> NamedSharding:
    """Leading (batch) axis over ("data", "fsdp"), the rest replicated."""
    return NamedSharding(mesh, PartitionSpec(BATCH_AXES))


def replicated(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, PartitionSpec())


def check_batch_size(global_batch: int, mesh: Mesh, what: str = "batch_size") -> int:
    """Per-process batch size; raises when the global batch does not split evenly."""
    n_dev, n_proc = mesh.devices.size, jax.process_count()
    if global_batch % n_dev:
        raise ValueError(
            f"{what}={global_batch} is not divisible by the {n_dev} devices of the mesh; use a "
            f"multiple of {n_dev}")
    return global_batch // n_proc


def global_batch(local: dict[str, np.ndarray], mesh: Mesh) -> dict[str, jax.Array]:
    """This process's slice of a batch -> global arrays sharded over the batch axes."""
    sharding = batch_sharding(mesh)
    return {k: jax.make_array_from_process_local_data(sharding, np.asarray(v))
            for k, v in local.items()}
