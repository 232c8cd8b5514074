"""Evaluate a trained run: ``python -m experiments.evaluate --checkpoint RUN_DIR [--episodes 50]``.

``RUN_DIR`` is a train output dir (``checkpoints/``, ``inference.json``, ``calibration.json``) or its
``checkpoints/`` dir. The policy (EMA parameters) and its task come from the checkpoint; the inference settings
default to the run's ``inference.json`` (so the numbers reproduce training's evaluation), each overridable
(``--inference.num-samples 100 --inference.sampler ddpm``); the thresholds come from ``calibration.json``
(``python -m experiments.calibrate``) unless ``--inference.thresholds`` gives them (M+1 values, or the M-1 inner
ones). The same episodes (same initial states) run twice in one compiled batched rollout: with entropy-guided
execution and without it (always stride 1). With the defaults the entropy-guided numbers reproduce the final
evaluation ``experiments.train`` reported (same settings, same initial states). Writes into ``RUN_DIR/eval/`` (or
``--out``):

- ``eval.json``: success rate, mean execution steps (all / successful episodes), stride fractions, per episode
  success and steps, for both evaluations, and the settings used; on a task whose success needs a phase to last
  (press_button's hold), ``timed_phase``: how many episodes hold it long enough, and its durations per executed
  stride (``evaluation.phases``);
- ``entropy_trace.png``: per-replan action entropy over control time for a few episodes, the executed stride as
  background bands and the thresholds as lines (the paper's entropy curve);
- ``rollout.mp4`` (``rollout.gif`` without ffmpeg): the first successful episode (else the first), annotated with
  the stride and entropy of the chunk being executed.

A run of an external task (``metaworld:<task>``) is evaluated in its own simulator through the policy server
(``runs.external.evaluate_report``; its venv: ``bash scripts/setup_metaworld.sh``): the same two passes, on
initial-state seeds 1,000,000 + 1000·seed + i (the Meta-World campaign's episodes of that training seed), and
``eval.json`` only.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Literal

from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.envs.external import is_external
from hipolicy_jax.runs.cli import prepare_process, run_main
from hipolicy_jax.runs.evaluate import evaluate_run
from hipolicy_jax.runs.external import evaluate_report
from hipolicy_jax.runs.store import load_run, with_compute_dtype


@dataclasses.dataclass(frozen=True)
class EvaluateArgs:
    checkpoint: str  # run dir (holding checkpoints/ and calibration.json) or its checkpoints/ dir
    step: int | None = None  # checkpoint step (default: the latest)
    episodes: int = 20  # 20 = experiments.train's default --eval.episodes
    inference: InferenceConfig = InferenceConfig()  # default: the run's inference.json
    seed: int | None = None  # evaluation episodes come from eval_key(seed); default the run's training seed, whose
    # initial states training evaluated on: the defaults reproduce the final evaluation of experiments.train
    compute_dtype: Literal["run", "float32", "bfloat16"] = "run"  # the U-Net's operand dtype (model.compute_dtype);
    # run: as trained. bfloat16 evaluates the same float32 parameters with bf16 convolution / attention operands
    out: str = ""  # default RUN_DIR/eval
    trace_episodes: int = 4  # episodes drawn in entropy_trace.png
    video: Literal["auto", "mp4", "gif", "none"] = "auto"  # auto: mp4 when ffmpeg is installed, else gif
    video_backend: Literal["auto", "opengl", "raycast"] = "auto"
    video_height: int = 240
    video_width: int = 320


def _line(name: str, s: dict) -> str:
    strides = ", ".join(f"{k[6:-5]}: {v:.2f}" for k, v in s.items() if k.startswith("stride") and k.endswith("_frac"))
    counts = "".join(f", {s[k]:.1f} {what}" for k, what in (("mean_decisions", "decisions"),
                                                          ("mean_actions", "actions")) if k in s)
    return (f"  {name:<34} success {s['success_rate']:.2f}, mean control steps {s['mean_steps']:.1f} "
            f"(successful: {s['mean_steps_success']:.1f}){counts}; stride fractions {{{strides}}}")


def _timed_line(name: str, t: dict) -> str:
    by = "; ".join(f"stride {s}: {v['runs']} runs, median {v['median_steps']:g} steps, {v['reached']:.0%} long enough"
                   for s, v in t["by_stride"].items())
    return (f"  timed phase, {name}: {t['reached']:.0%} of episodes hold it {t['required_steps']} steps; {by}")


def main_external(args: EvaluateArgs, run) -> dict:
    if args.compute_dtype != "run":
        raise ValueError(f"compute_dtype: {run.task} runs are served as trained, got {args.compute_dtype!r}")
    seed = run.seed if args.seed is None else args.seed
    report = evaluate_report(run.run_dir, args.inference, episodes=args.episodes, seed=seed, step=args.step,
                             out=args.out)
    print(f"{run.task} @ step {report['checkpoint_step']}, {args.episodes} episodes (initial-state seeds "
          f"{report['seeds'][0]}...), N={args.inference.num_samples}, thresholds from {report['thresholds_source']}: "
          f"{[round(t, 3) for t in report['thresholds']]}")
    print(_line("with entropy-guided execution", report["with_eg"]))
    print(_line("without (always stride 1)", report["without_eg"]))
    print(f"outputs in {args.out or os.path.join(run.run_dir, 'eval')}: eval.json (episodes run in the task's own "
          f"simulator through the policy server: no video or entropy plot)")
    return report


def main(args: EvaluateArgs) -> dict:
    run = load_run(args.checkpoint, args.step)
    if is_external(run.task):
        return main_external(args, run)
    run = with_compute_dtype(run, args.compute_dtype)
    seed = run.seed if args.seed is None else args.seed
    report = evaluate_run(run, args.inference, episodes=args.episodes, seed=seed, out=args.out,
                          trace_episodes=args.trace_episodes, video_format=args.video,
                          video_backend=args.video_backend, video_height=args.video_height,
                          video_width=args.video_width)
    print(f"{run.task} @ step {run.policy.step}, {args.episodes} episodes, N={args.inference.num_samples}, "
          f"thresholds from {report['thresholds_source']}: {[round(t, 3) for t in report['thresholds']]}")
    print(_line("with entropy-guided execution", report["with_eg"]))
    print(_line("without (always stride 1)", report["without_eg"]))
    for name, key in (("with entropy-guided execution", "with_eg"), ("without (always stride 1)", "without_eg")):
        if "timed_phase" in report[key]:
            print(_timed_line(name, report[key]["timed_phase"]))
    out = os.path.dirname(report["files"]["trace"])
    print(f"outputs in {out}: eval.json, " + ", ".join(os.path.basename(f) for f in report["files"].values()))
    return report


if __name__ == "__main__":
    prepare_process()
    run_main(EvaluateArgs, main, __doc__)
