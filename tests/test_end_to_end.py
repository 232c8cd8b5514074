"""Tiny end to end run of the main job: collect demos → train a few steps → calibrate → batched MJX rollouts."""

import dataclasses
import json
import math

import numpy as np
import pytest
from helpers import xla_compiles

from hipolicy_jax.config import EvalConfig, InferenceConfig, ModelConfig, PolicyConfig, TrainConfig
from hipolicy_jax.runs.store import read_inference
from hipolicy_jax.runs.train import RunConfig, main


def test_train_calibrate_evaluate_tiny(tmp_path):
    args = RunConfig(
        task="press_button", out=str(tmp_path / "run"), data=str(tmp_path / "demos.zarr"), episodes=6,
        val_ratio=0.34, policy=PolicyConfig(model=ModelConfig(size="tiny", fusion_heads=2)),
        train=TrainConfig(batch_size=16, num_steps=12, warmup_steps=2, log_every=6, ckpt_every=6),
        eval=EvalConfig(episodes=3, every=6), inference=InferenceConfig(num_samples=4, num_steps=2, calib_windows=16),
        progress=False)
    with xla_compiles() as compiled:
        summary = main(args)

    assert summary["steps"] == 12
    assert 0.0 < summary["cpu_time_s"] and 0.0 < summary["wall_time_s"]  # process CPU time: what the run cost
    assert 0.0 <= summary["eval"]["success_rate"] <= 1.0
    th = summary["thresholds"]
    assert len(th) == 4 and th[0] == -math.inf and th[-1] == math.inf and th[1] < th[2]
    fracs = [v for k, v in summary["eval"].items() if k.startswith("stride")]
    assert math.isclose(sum(fracs), 1.0, rel_tol=1e-6)

    def strict(text):  # every file the run wrote is standard JSON (no NaN / Infinity constants)
        return json.loads(text, parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))

    for path in (tmp_path / "run").glob("*.json"):
        strict(path.read_text())
    rows = [strict(x) for x in open(tmp_path / "run" / "metrics.jsonl")]
    assert [r["step"] for r in rows if r["kind"] == "eval"] == [6, 12]
    assert all(np.isfinite(r["loss"]) for r in rows if r["kind"] == "train")
    assert (tmp_path / "run" / "calibration.json").exists() and (tmp_path / "run" / "summary.json").exists()
    assert read_inference(str(tmp_path / "run")) == args.inference
    # two evaluations (steps 6 and 12, the final one reused) with new parameters each: one compiled rollout
    assert sum("jit(rollout" in name for name in compiled) == 1, compiled

    # experiments.evaluate's defaults (the run's inference.json, its training seed) reproduce the final evaluation
    from experiments import evaluate

    report = evaluate.main(evaluate.EvaluateArgs(checkpoint=str(tmp_path / "run"), episodes=3, video="none",
                                                 inference=read_inference(str(tmp_path / "run"))))
    for k in ("success_rate", "mean_steps", "stride1_frac"):
        assert report["with_eg"].get(k) == summary["eval"].get(k), k

    # re-running the finished command resumes at the end, whatever the inference settings: no training steps
    again = main(dataclasses.replace(args, inference=InferenceConfig(num_samples=3, num_steps=1, calib_windows=8)))
    assert again["steps"] == 12
    assert read_inference(str(tmp_path / "run")).num_samples == 3

    # --dry-run validates and reports without training
    info = main(dataclasses.replace(args, dry_run=True))
    assert info["param_count"] > 0 and info["episodes"] == 6
    assert info["batch"]["action"] == [16, 24, 4] and info["batch"]["obs.state"][:3] == [16, 3, 3]
