"""Evaluate a trained run: the same episodes with and without entropy-guided execution, traces and a video.

``evaluate_run`` loads nothing itself: it takes a ``Run`` (``store.load_run``) and an ``InferenceConfig`` (by
default the run's stored one, so the numbers reproduce training's evaluation), rolls out the same initial states
twice in ONE compiled rollout (with entropy guidance and always at the highest frequency), and writes into
``out``: ``eval.json`` (success, steps, stride fractions, per-episode outcomes, the settings), ``entropy_trace.png``
and a rollout video of the first successful entropy-guided episode (mp4, or gif without ffmpeg).
"""

from __future__ import annotations

import dataclasses
import os

from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.evaluation import calibration, phases, plots, video
from hipolicy_jax.evaluation.evaluator import Evaluator, result_record
from hipolicy_jax.runs.store import Run, eval_key, make_evaluator, write_json


def evaluate_run(run: Run, inference: InferenceConfig, *, episodes: int = 20, seed: int = 0, out: str = "",
                 trace_episodes: int = 4, video_format: str = "auto", video_backend: str = "auto",
                 video_height: int = 240, video_width: int = 320, evaluator: Evaluator | None = None) -> dict:
    """Evaluate ``run`` on ``episodes`` episodes from ``eval_key(seed)``; → the report written to eval.json.

    ``video_format``: 'mp4', 'gif', 'auto' (mp4 when an ffmpeg backend is installed) or 'none'. ``evaluator``:
    reuse one (e.g. across checkpoints of the run) instead of building (and compiling) a new one.
    """
    cfg = run.policy.cfg
    out = out or os.path.join(run.run_dir, "eval")
    os.makedirs(out, exist_ok=True)
    calib = calibration.read_calibration(run.run_dir)
    thresholds, source = calibration.resolve_thresholds(inference, cfg.chunk.num_freqs, calib)
    ev = evaluator or make_evaluator(run, inference)
    p, key = run.policy, eval_key(seed)
    eg, rec = ev.rollout(p.params, p.normalizer, episodes, key, thresholds, entropy_guided=True)
    plain, plain_rec = ev.rollout(p.params, p.normalizer, episodes, key, thresholds, entropy_guided=False)
    percentiles = calib.get("percentiles") if (calib and source == calibration.CALIBRATION_FILE) else None
    files = {"trace": plots.plot_entropy_traces(
        eg, thresholds, cfg.chunk.strides, os.path.join(out, "entropy_trace.png"),
        episodes=trace_episodes, percentiles=percentiles,
        title=f"{run.task} @ step {p.step}: entropy-guided execution, thresholds from {source}")}
    video_episode = None
    fmt = video.resolve_format(video_format)
    if fmt != "none":
        files["video"], video_episode = video.save_episode_video(
            ev.env, eg, rec, os.path.join(out, f"rollout.{fmt}"), backend=video_backend, height=video_height,
            width=video_width)
    with_eg, without_eg = result_record(eg), result_record(plain)
    for record, result, recording in ((with_eg, eg, rec), (without_eg, plain, plain_rec)):
        timed = phases.timed_phase_report(ev.env, result, recording)
        if timed is not None:
            record["timed_phase"] = timed
    report = {"task": run.task, "run_dir": run.run_dir, "checkpoint_step": p.step, "strides": list(cfg.chunk.strides),
              "objective": cfg.objective, "episodes": episodes, "seed": seed,
              "inference": dataclasses.asdict(inference), "thresholds": list(thresholds), "thresholds_source": source,
              "with_eg": with_eg, "without_eg": without_eg,
              "steps_ratio": with_eg["mean_steps"] / without_eg["mean_steps"], "video_episode": video_episode,
              "files": files}
    write_json(os.path.join(out, "eval.json"), report)
    return report
