"""Tiny end to end run of the main job: collect demos → train a few steps → calibrate → batched MJX rollouts."""

import dataclasses
import json
import math

import numpy as np

from experiments.common import EvalOptions
from experiments.train import TrainArgs, main
from hipolicy_jax.config import ModelConfig, PolicyConfig, SamplingConfig, TrainConfig
from hipolicy_jax.envs import rollout


def test_train_calibrate_evaluate_tiny(tmp_path):
    args = TrainArgs(
        task="press_button", out=str(tmp_path / "run"), data=str(tmp_path / "demos.zarr"), episodes=6,
        val_ratio=0.34,
        policy=PolicyConfig(model=ModelConfig(size="tiny", fusion_heads=2), sampling=SamplingConfig(num_samples=4)),
        train=TrainConfig(batch_size=16, num_steps=12, warmup_steps=2, log_every=6, ckpt_every=6),
        eval=EvalOptions(episodes=3, num_samples=4, num_steps=2, every=6, calib_windows=16),
        progress=False)
    compiled_before = rollout.compiled_rollout.cache_info().currsize
    summary = main(args)

    assert summary["steps"] == 12
    assert 0.0 <= summary["eval"]["success_rate"] <= 1.0
    th = summary["thresholds"]
    assert len(th) == 4 and th[0] == -math.inf and th[-1] == math.inf and th[1] < th[2]
    fracs = [v for k, v in summary["eval"].items() if k.startswith("stride")]
    assert math.isclose(sum(fracs), 1.0, rel_tol=1e-6)

    rows = [json.loads(x) for x in open(tmp_path / "run" / "metrics.jsonl")]
    assert [r["step"] for r in rows if r["kind"] == "eval"] == [6, 12]
    assert all(np.isfinite(r["loss"]) for r in rows if r["kind"] == "train")
    assert (tmp_path / "run" / "calibration.json").exists() and (tmp_path / "run" / "summary.json").exists()
    # three evaluations (step 6, step 12, final) with new parameters each: one compiled rollout
    assert rollout.compiled_rollout.cache_info().currsize - compiled_before == 1

    # re-running the finished command resumes at the end: no training steps, same checkpoint
    again = main(args)
    assert again["steps"] == 12

    # --dry-run validates and reports without training
    info = main(dataclasses.replace(args, dry_run=True))
    assert info["param_count"] > 0 and info["episodes"] == 6
    assert info["batch"]["action"] == [16, 24, 4] and info["batch"]["obs.state"][:3] == [16, 3, 3]
