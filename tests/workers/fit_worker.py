"""Subprocess worker for tests: trains the tiny synthetic policy and prints per-step losses as JSON.

python tests/workers/fit_worker.py OUT_DIR --steps 16 [--devices 4] [--sleep 0.2]
(--sleep slows every batch so a test can kill the process mid-run.)
"""

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from test_training import bimodal_buffer, tiny_cfg  # noqa: E402

from hipolicy_jax.config import TrainConfig  # noqa: E402
from hipolicy_jax.data.dataset import SequenceDataset  # noqa: E402
from hipolicy_jax.trainer import TrainingInterrupted, fit  # noqa: E402


class SlowDataset:
    """Delegates to a dataset, sleeping before every batch."""

    def __init__(self, inner, sleep):
        self._inner, self._sleep = inner, sleep

    def __getattr__(self, name):
        return getattr(self._inner, name)

    def __len__(self):
        return len(self._inner)

    def get_batch(self, idx):
        time.sleep(self._sleep)
        return self._inner.get_batch(idx)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--steps", type=int, default=16)
    ap.add_argument("--devices", type=int, default=None)
    ap.add_argument("--sleep", type=float, default=0.0)
    ap.add_argument("--batch", type=int, default=16)
    a = ap.parse_args()
    ds = SequenceDataset(bimodal_buffer(), tiny_cfg().chunk, obs_keys=("state",))
    if a.sleep:
        ds = SlowDataset(ds, a.sleep)
    train_cfg = TrainConfig(batch_size=a.batch, num_steps=a.steps, warmup_steps=2, log_every=1, ckpt_every=4)
    try:  # as experiments.train: an interrupt ends the process with 128 + the signal number
        res = fit(tiny_cfg(), train_cfg, ds, a.out, progress=False, tensorboard=False, num_devices=a.devices)
    except TrainingInterrupted as e:
        print(f"interrupted by {e}", file=sys.stderr, flush=True)
        sys.exit(128 + e.signum)
    print(json.dumps({"start": res.start_step, "losses": res.losses, "devices": res.meta["num_devices"]}), flush=True)


if __name__ == "__main__":
    main()
