"""Subprocess worker: one process of a multi-process training of the tiny synthetic policy (CPU, gloo).

JAX_COORDINATOR_ADDRESS=127.0.0.1:PORT JAX_NUM_PROCESSES=2 JAX_PROCESS_ID=i JAX_NUM_CPU_DEVICES=2 \\
    python tests/workers/dist_worker.py OUT_DIR --steps 20 [--stop-at 10]

Prints one JSON line: the process index and count, the global device count, the step it started from, its losses
and, for the first global batch, the rows of it this process holds (its slice of the batch).
"""

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from hipolicy_jax import parallel  # noqa: E402

parallel.initialize_distributed()  # before anything touches a device

import jax  # noqa: E402
import numpy as np  # noqa: E402
from test_training import bimodal_buffer, tiny_cfg  # noqa: E402

from hipolicy_jax.config import TrainConfig  # noqa: E402
from hipolicy_jax.data.dataset import SequenceDataset  # noqa: E402
from hipolicy_jax.trainer import fit, run_keys  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--stop-at", type=int, default=None)
    a = ap.parse_args()
    ds = SequenceDataset(bimodal_buffer(), tiny_cfg().chunk, obs_keys=("state",))
    train_cfg = TrainConfig(batch_size=16, num_steps=a.steps, warmup_steps=2, log_every=1, ckpt_every=5)
    res = fit(tiny_cfg(), train_cfg, ds, a.out, progress=False, tensorboard=False, stop_at=a.stop_at)
    idx = ds.batch_indices(run_keys(train_cfg.seed)["data"], 0, train_cfg.batch_size)
    local = parallel.shard_batch({"i": idx.astype(np.int32)}, parallel.make_mesh())["i"]
    mine = sorted(int(v) for shard in local.addressable_shards for v in np.asarray(shard.data))
    print(json.dumps({"process": jax.process_index(), "processes": jax.process_count(), "devices": jax.device_count(),
                      "start": res.start_step, "losses": res.losses, "global_batch": idx.tolist(),
                      "local_rows": mine}), flush=True)


if __name__ == "__main__":
    main()
