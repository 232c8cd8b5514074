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
    """``jax.distributed.initialize()`` when the launcher set the coordinator variables; → whether it did."""
    if os.environ.get("JAX_COORDINATOR_ADDRESS") and jax.process_count() == 1:
        jax.distributed.initialize()
        return True
    return False


def make_mesh(num_devices: int | None = None) -> Mesh | None:
    """A 1-D ``("data",)`` mesh over the first ``num_devices`` devices (default all); None for a single device."""
    devices = jax.devices()
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
    if jax.process_count() == 1:
        return jax.device_put(batch, sharding)

    def local(x):
        per = x.shape[0] // jax.process_count()
        mine = x[jax.process_index() * per:(jax.process_index() + 1) * per]
        return jax.make_array_from_process_local_data(sharding, mine, x.shape)

    return jax.tree.map(local, batch)
