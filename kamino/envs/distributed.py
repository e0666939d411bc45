"""Training across processes and hosts: JAX's multi-process runtime (``jax.distributed``), one process per host (or
per GPU), each driving its local devices.

Brax's PPO runs unchanged across processes. Each process steps ``num_envs / process_count`` environments on its
local devices (Brax folds the process index into their keys), and its ``pmap`` averages the gradients and the
observation statistics over every device of every process, so that every process holds the same parameters after
every update. Process 0 alone evaluates, reports and is handed the parameters at an evaluation; ``kamino train``
writes the run folder there only (:func:`kamino.envs.runs.write_checkpoint_alone`), and the other processes read it,
which needs a run folder on a file system every process sees. What Brax reports: the environment steps and the
steps per second are those of all processes; the losses and the training episodes (``--train-returns``) are those of
process 0's environments.

``kamino train --distributed`` starts the runtime (:func:`initialize`); docs/envs.md ("Several hosts") shows the
launch on a cluster. tests/test_rl_distributed.py trains with two CPU processes on one machine.
"""

from __future__ import annotations


def initialize(coordinator: str | None = None, num_processes: int | None = None,
               process_id: int | None = None) -> int:
    """Start JAX's multi-process runtime before any JAX computation, and return this process's index.

    ``coordinator`` (``host:port`` of process 0), ``num_processes`` and ``process_id`` are those of
    ``jax.distributed.initialize``. Given all three, the process drives all its local devices and JAX detects
    nothing from the cluster. Left ``None``, JAX takes them from the cluster it runs in (SLURM, Open MPI) or from
    ``JAX_COORDINATOR_ADDRESS``; JAX's SLURM detection then gives each process one device, the GPU of its
    ``SLURM_LOCALID``, unless ``JAX_LOCAL_DEVICE_IDS`` lists the devices.

    Processes on CPUs exchange their collectives through gloo (JAX's CPU collectives), so that two CPU processes on
    one machine train together as two GPU hosts do. ``pmap`` stays JAX's own (``jax_pmap_shmap_merge`` off): Brax
    averages its epoch's metrics with ``jnp.mean`` over ``pmap``'s outputs, which are this process's devices' under
    that ``pmap``, and arrays over every process's devices (not addressable here) under the ``shard_map`` one."""
    import jax

    if (num_processes is None) != (process_id is None):
        raise ValueError("kamino.envs.distributed.initialize: give num_processes and process_id together "
                         f"(got num_processes={num_processes}, process_id={process_id})")
    if num_processes is not None and not 0 <= process_id < num_processes:
        raise ValueError(f"kamino.envs.distributed.initialize: process_id must be in [0, {num_processes}), "
                         f"got {process_id}")
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    if "jax_pmap_shmap_merge" in jax.config.values:  # the JAX releases that still have it
        jax.config.update("jax_pmap_shmap_merge", False)
    explicit = None not in (coordinator, num_processes, process_id)
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes, process_id=process_id,
                               cluster_detection_method="deactivate" if explicit else None)
    return jax.process_index()


def synchronize(name: str) -> None:
    """Wait until every process has called ``synchronize`` with the same ``name`` (a barrier of the multi-process
    runtime; nothing to wait for in one process)."""
    import jax

    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


def same_everywhere(value: int, what: str) -> None:
    """Raise ``ValueError`` on every process unless the integer ``value`` is the same on all of them (``what`` names
    it in the message): the processes of one training must agree on what they read from the run folder."""
    import jax
    import numpy as np

    if jax.process_count() == 1:
        return
    from jax.experimental import multihost_utils

    seen = np.asarray(multihost_utils.process_allgather(np.asarray(value, np.int32))).ravel().tolist()
    if len(set(seen)) > 1:
        raise ValueError(f"the processes disagree on {what}: {seen} (process 0, 1, ...)")
