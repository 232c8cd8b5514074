"""Evaluate a trained run: ``python -m experiments.evaluate --checkpoint RUN_DIR [--episodes 50]``.

``RUN_DIR`` is a train output dir (``checkpoints/`` + ``calibration.json``) or its ``checkpoints/`` dir. The
policy (EMA parameters) and its task come from the checkpoint; the entropy thresholds from ``calibration.json``
(``python -m experiments.calibrate``) or ``--thresholds`` (M+1 values, or the M-1 inner ones). The same episodes
(same initial states) run twice in one compiled batched rollout: with entropy-guided execution and without it
(always the highest frequency, stride 1). Writes into ``RUN_DIR/eval/`` (or ``--out``):

- ``eval.json``: success rate, mean execution steps (all / successful episodes), stride fractions, per episode
  success and steps, for both evaluations, and the settings used;
- ``entropy_trace.png``: per-replan action entropy over control time for a few episodes, the executed stride as
  background bands and the thresholds as lines (the paper's entropy curve);
- ``rollout.gif``: the learned policy's first successful episode (else the first), annotated with the stride and
  entropy of the chunk being executed.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Literal

import numpy as np
import tyro

from experiments.common import (EvalOptions, Run, eval_key, eval_summary, evaluate_policy_recorded, load_run,
                                policy_env, read_calibration, run_action_dim, write_json)


@dataclasses.dataclass(frozen=True)
class EvaluateArgs:
    checkpoint: str  # run dir (holding checkpoints/ and calibration.json) or its checkpoints/ dir
    step: int | None = None  # checkpoint step (default: the latest)
    episodes: int = 20
    num_samples: int = 16  # N for the entropy estimate
    sampler: Literal["ddpm", "ddim"] = "ddim"
    num_steps: int = 10  # denoising steps
    thresholds: tuple[float, ...] | None = None  # M+1 (or M-1 inner) entropy thresholds; default calibration.json
    seed: int = 0  # evaluation episodes come from eval_key(seed)
    out: str = ""  # default RUN_DIR/eval
    trace_episodes: int = 4  # episodes drawn in entropy_trace.png
    video: bool = True
    video_backend: Literal["auto", "opengl", "raycast"] = "auto"
    video_height: int = 240
    video_width: int = 320

    def options(self, entropy_guided: bool = True) -> EvalOptions:
        return EvalOptions(episodes=self.episodes, num_samples=self.num_samples, sampler=self.sampler,
                           num_steps=self.num_steps, every=0, entropy_guided=entropy_guided)


def resolve_thresholds(run: Run, override: tuple[float, ...] | None = None) -> tuple[tuple[float, ...], str]:
    """(M+1 thresholds, where they came from): ``override`` (M+1 values or the M-1 inner ones), the run's
    ``calibration.json``, or (-inf, +inf) for a single-frequency policy."""
    m = run.policy.cfg.chunk.num_freqs
    if override is not None:
        th = tuple(float(x) for x in override)
        if len(th) == m - 1:
            th = (-np.inf, *th, np.inf)
        if len(th) != m + 1 or any(a >= b for a, b in zip(th, th[1:])):
            raise ValueError(f"thresholds: need M+1={m + 1} (or M-1={m - 1} inner) ascending values for M={m}, "
                             f"got {override}")
        return th, "--thresholds"
    if m == 1:
        return (-np.inf, np.inf), "single frequency (no thresholds needed)"
    calib = read_calibration(run.run_dir)
    if calib is None:
        raise FileNotFoundError(f"{run.run_dir}/calibration.json is missing: run `python -m experiments.calibrate "
                                f"--checkpoint {run.run_dir}` or pass --thresholds")
    th = tuple(float(x) for x in calib["thresholds"])
    if len(th) != m + 1:
        raise ValueError(f"{run.run_dir}/calibration.json: {len(th)} thresholds, the policy has M={m} frequencies")
    return th, "calibration.json"


def evaluate_guided_pair(run: Run, opts: EvalOptions, key, thresholds) -> dict:
    """Roll out the same episodes with and without entropy guidance (one compiled rollout serves both).

    → {"with_eg": (EvalResult, Recording), "without_eg": (EvalResult, Recording)}.
    """
    p = run.policy
    out = {}
    for name, guided in (("with_eg", True), ("without_eg", False)):
        out[name] = evaluate_policy_recorded(p.net, p.params, p.normalizer, p.cfg, run_action_dim(run), run.task,
                                             dataclasses.replace(opts, entropy_guided=guided), key,
                                             thresholds=thresholds)
    return out


def result_record(result) -> dict:
    """``eval_summary`` plus per-episode success and steps."""
    return {**eval_summary(result), "success": [bool(x) for x in np.asarray(result.success)],
            "steps": [int(x) for x in np.asarray(result.steps)]}


def plot_entropy_traces(result, thresholds, strides: tuple[int, ...], chunk_len: int, path: str, *,
                        episodes: int = 4, title: str = "", percentiles=None) -> str:
    """PNG of per-replan entropy over control steps for the first ``episodes`` episodes of an ``EvalResult``:
    the executed stride as background bands, the finite thresholds as dashed lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    from hipolicy_jax.envs.video import stride_color

    ent, stride, valid = (np.asarray(x) for x in (result.entropy, result.stride, result.valid))
    success, steps = np.asarray(result.success), np.asarray(result.steps)
    n = max(1, min(episodes, ent.shape[0]))
    fig, axes = plt.subplots(n, 1, figsize=(8, 1.9 * n + 0.8), sharex=True, squeeze=False)
    inner = [(k, t) for k, t in enumerate(thresholds) if np.isfinite(t)]
    finite = ent[valid & np.isfinite(ent)]
    for e, ax in enumerate(axes[:, 0]):
        rs = np.flatnonzero(valid[e])
        for r in rs:
            color = np.array(stride_color(stride[e, r])) / 255
            ax.axvspan(r * chunk_len, min((r + 1) * chunk_len, steps[e]), color=color, alpha=0.25, lw=0, zorder=0)
        if rs.size and np.isfinite(ent[e, rs]).any():
            x = np.append(rs * chunk_len, min((rs[-1] + 1) * chunk_len, steps[e]))
            y = np.append(ent[e, rs], ent[e, rs[-1]])
            ax.step(x, y, where="post", color="k", lw=1.2)
            ax.plot(rs * chunk_len, ent[e, rs], "k.", ms=4)
        for k, t in inner:
            label = f"th{k}" + (f" (p{percentiles[k - 1]:g})" if percentiles and 0 < k <= len(percentiles) else "")
            ax.axhline(t, color="gray", ls="--", lw=0.9)
            ax.text(1.0, t, " " + label, transform=ax.get_yaxis_transform(), va="center", fontsize=7, color="gray")
        if finite.size:
            lo, hi = float(finite.min()), float(finite.max())
            for _, t in inner:
                lo, hi = min(lo, t), max(hi, t)
            pad = 0.1 * max(hi - lo, 1e-3)
            ax.set_ylim(lo - pad, hi + pad)
        ax.set_ylabel("entropy")
        ax.set_title(f"episode {e}: {'success' if success[e] else 'failure'} in {int(steps[e])} steps", fontsize=9)
    axes[-1, 0].set_xlabel("control step")
    handles = [Patch(color=np.array(stride_color(s)) / 255, alpha=0.4, label=f"stride {s}") for s in strides]
    fig.legend(handles=handles, loc="lower center", ncol=len(strides), fontsize=8, frameon=False)
    fig.suptitle(title or "action entropy per replan", fontsize=10)
    fig.tight_layout(rect=(0, 0.04, 0.95, 1.0))
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def save_rollout_video(run: Run, result, recording, path: str, *, backend: str = "auto", height: int = 240,
                       width: int = 320) -> tuple[str, int]:
    """Render the first successful episode (else episode 0) of a recorded rollout → (path, episode index)."""
    from hipolicy_jax.envs import video

    success = np.asarray(result.success)
    episode = int(np.argmax(success)) if success.any() else 0
    cfg = run.policy.cfg
    traj = video.trajectory_from_rollout(result, recording, episode, cfg.chunk.chunk_len)
    env = policy_env(run.task, cfg.encoder)
    frames = video.render_frames(env, traj, height=height, width=width, backend=backend)
    video.save_video(video.annotate_frames(frames, traj), path, 1.0 / env.control_dt)
    return path, episode


def _line(name: str, s: dict) -> str:
    strides = ", ".join(f"{k[6:-5]}: {v:.2f}" for k, v in s.items() if k.startswith("stride") and k.endswith("_frac"))
    return (f"  {name:<34} success {s['success_rate']:.2f}, mean steps {s['mean_steps']:.1f} "
            f"(successful: {s['mean_steps_success']:.1f}); stride fractions {{{strides}}}")


def main(args: EvaluateArgs) -> dict:
    run = load_run(args.checkpoint, args.step)
    cfg = run.policy.cfg
    out = args.out or os.path.join(run.run_dir, "eval")
    os.makedirs(out, exist_ok=True)
    thresholds, source = resolve_thresholds(run, args.thresholds)
    pair = evaluate_guided_pair(run, args.options(), eval_key(args.seed), thresholds)
    (eg, rec), (plain, _) = pair["with_eg"], pair["without_eg"]
    calib = read_calibration(run.run_dir) or {}
    percentiles = calib.get("percentiles") if source == "calibration.json" else None
    files = {"trace": plot_entropy_traces(
        eg, thresholds, cfg.chunk.strides, cfg.chunk.chunk_len, os.path.join(out, "entropy_trace.png"),
        episodes=args.trace_episodes, percentiles=percentiles,
        title=f"{run.task} @ step {run.policy.step}: entropy-guided execution, thresholds from {source}")}
    video_episode = None
    if args.video:
        files["video"], video_episode = save_rollout_video(run, eg, rec, os.path.join(out, "rollout.gif"),
                                                           backend=args.video_backend, height=args.video_height,
                                                           width=args.video_width)
    with_eg, without_eg = result_record(eg), result_record(plain)
    report = {"task": run.task, "run_dir": run.run_dir, "checkpoint_step": run.policy.step,
              "strides": list(cfg.chunk.strides), "episodes": args.episodes, "num_samples": args.num_samples,
              "sampler": args.sampler, "num_steps": args.num_steps, "seed": args.seed,
              "thresholds": list(thresholds), "thresholds_source": source,
              "with_eg": with_eg, "without_eg": without_eg,
              "steps_ratio": with_eg["mean_steps"] / without_eg["mean_steps"], "video_episode": video_episode,
              "files": files}
    write_json(os.path.join(out, "eval.json"), report)
    print(f"{run.task} @ step {run.policy.step}, {args.episodes} episodes, thresholds {source}: "
          f"{[round(t, 3) for t in thresholds]}")
    print(_line("with entropy-guided execution", with_eg))
    print(_line("without (always stride 1)", without_eg))
    print(f"outputs in {out}: eval.json, " + ", ".join(os.path.basename(f) for f in files.values()))
    return report


if __name__ == "__main__":
    main(tyro.cli(EvaluateArgs, description=__doc__))
