"""Data parallelism over local (and, when launched so, multi-host) devices with ``jax.sharding``.

One mesh axis ``"data"``: batches are split along their leading axis, parameters and optimiser state are
replicated, and XLA inserts the gradient all-reduce. The model has no batch statistics (GroupNorm, LayerNorm), so
a sharded step computes the same loss as a single-device step on the same global batch, up to float reduction
order. With one device everything is a no-op.

Multi-host: when ``JAX_COORDINATOR_ADDRESS`` (with ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID``) is set,
``initialize_distributed`` calls ``jax.distributed.initialize``; every process draws the same global batch indices
and contributes its own slice (``shard_batch``).
"""

from __future__ import annotations

import os

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P


def initialize_distributed() -> bool:
    """Join a multi-process run when the launcher set ``JAX_COORDINATOR_ADDRESS`` (``host:port`` of process 0),
    ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID``; CPU processes exchange gradients over gloo. Must run before
    anything touches a JAX device. → whether it initialised (False: a single-process run).

    One machine, 2 processes of 2 CPU devices each::

        for i in 0 1; do JAX_COORDINATOR_ADDRESS=127.0.0.1:12355 JAX_NUM_PROCESSES=2 JAX_PROCESS_ID=$i \\
            JAX_NUM_CPU_DEVICES=2 python -m experiments.train --out runs/mp & done; wait
    """
    address = os.environ.get("JAX_COORDINATOR_ADDRESS")
    if not address or jax.distributed.is_initialized():
        return False
    missing = [k for k in ("JAX_NUM_PROCESSES", "JAX_PROCESS_ID") if k not in os.environ]
    if missing:
        raise ValueError(f"JAX_COORDINATOR_ADDRESS={address} is set but {', '.join(missing)} is not: set the number "
                         f"of processes and this process's index (0 .. N-1)")
    jax.config.update("jax_cpu_collectives_implementation", "gloo")  # CPU all-reduce across processes
    jax.distributed.initialize(coordinator_address=address, num_processes=int(os.environ["JAX_NUM_PROCESSES"]),
                               process_id=int(os.environ["JAX_PROCESS_ID"]))
    return True


def barrier(name: str) -> None:
    """Wait until every process of a multi-process run got here (no-op in a single process)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


def is_primary() -> bool:
    """Whether this process writes the run's files (logs, summaries, locks): process 0."""
    return jax.process_index() == 0


def to_host(tree):
    """NumPy copies of a pytree of (possibly multi-process, replicated) arrays: each process reads its own copy."""
    def one(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            return np.asarray(x.addressable_data(0))
        return np.asarray(x)

    return jax.tree.map(one, tree)


def make_mesh(num_devices: int | None = None, local: bool = False) -> Mesh | None:
    """A 1-D ``("data",)`` mesh over the first ``num_devices`` devices (default all, of every process; ``local``:
    this process's only); None for a single device."""
    devices = jax.local_devices() if local else jax.devices()
    n = len(devices) if num_devices is None else num_devices
    if not 1 <= n <= len(devices):
        raise ValueError(f"num_devices: must be in [1, {len(devices)}] (devices available), got {n}")
    if n == 1:
        return None
    return Mesh(np.asarray(devices[:n]), ("data",))


def check_batch_size(batch_size: int, mesh: Mesh | None) -> None:
    if mesh is not None and batch_size % mesh.size:
        raise ValueError(f"train.batch_size: {batch_size} must be divisible by the {mesh.size} devices of the mesh")


def replicate(tree, mesh: Mesh | None):
    """Place every leaf of ``tree`` on all mesh devices."""
    if mesh is None:
        return tree
    return jax.device_put(tree, NamedSharding(mesh, P()))


def shard_batch(batch, mesh: Mesh | None):
    """Split every leaf's leading (batch) axis across the mesh; ``batch`` is the global batch (numpy)."""
    if mesh is None:
        return batch
    sharding = NamedSharding(mesh, P("data"))
    if jax.process_count() == 1 or all(d.process_index == jax.process_index() for d in mesh.devices.flat):
        return jax.device_put(batch, sharding)  # every device of the mesh is this process's

    def local(x):
        per = x.shape[0] // jax.process_count()
        mine = x[jax.process_index() * per:(jax.process_index() + 1) * per]
        return jax.make_array_from_process_local_data(sharding, mine, x.shape)

    return jax.tree.map(local, batch)
