"""Success under inference delay: asynchronous execution (``--inference.delay d``) with the naive and the
prefix-inpainting hand-over, DP vs DP+HiPolicy.

    python -m benchmarks.delay                       # press_button and latch_door, d in 0 1 2 4, 100 episodes
    python -m benchmarks.delay --tasks press_button --delays 0 2 --episodes 20

For each task, trained run (``--runs TASK:LABEL:RUN_DIR``; default the cpu-budget DP and HiPolicy runs of
``experiments.paper`` under ``--runs-root``) and setting (d = 0 once: synchronous execution; d > 0 with each
hand-over), one closed-loop evaluation on the same initial states (``eval_key(--eval-seed)``) with the run's stored
inference settings and calibration: success rate, mean control steps of successful episodes, decisions per
episode. Writes ``benchmarks/results/delay_<device>.json`` (rows resume: a row is re-run only when missing or
its run / checkpoint / episodes changed) and ``delay_<device>.png`` (success and steps vs d).
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time

import numpy as np

from benchmarks.common import base_parser, device_kind, markdown_table, write_results
from hipolicy_jax import jsonio
from hipolicy_jax.evaluation import calibration
from hipolicy_jax.evaluation.evaluator import result_record
from hipolicy_jax.runs.store import eval_key, load_run, make_evaluator, run_inference

NAME = "delay"
DEFAULT_RUNS = {"DP": "state/dp/seed0", "DP+HiPolicy": "state/hipolicy/seed0"}


def parse_args(argv=None):
    p = base_parser(NAME, __doc__)
    p.add_argument("--tasks", nargs="+", default=["press_button", "latch_door"])
    p.add_argument("--delays", nargs="+", type=int, default=[0, 1, 2, 4])
    p.add_argument("--handovers", nargs="+", default=["naive", "inpaint"], choices=["naive", "inpaint"])
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--eval-seed", type=int, default=0)
    p.add_argument("--max-steps", type=int, default=None, help="episode step limit (default: the task's)")
    p.add_argument("--runs-root", default="runs/paper/cpu", help="experiments.paper's run root of the cpu budget")
    p.add_argument("--runs", nargs="*", default=None, metavar="TASK:LABEL:RUN_DIR",
                   help="explicit runs (default: DP and DP+HiPolicy of each task under --runs-root)")
    p.add_argument("--fresh", action="store_true", help="discard the existing JSON instead of resuming it")
    return p.parse_args(argv)


def run_paths(args) -> dict[tuple[str, str], str]:
    if args.runs:
        out = {}
        for spec in args.runs:
            task, label, path = spec.split(":", 2)
            out[(task, label)] = path
        return out
    return {(t, label): os.path.join(args.runs_root, t, rel) for t in args.tasks for label, rel in DEFAULT_RUNS.items()}


def settings(args) -> list[tuple[int, str]]:
    out = [(0, "sync")] if 0 in args.delays else []
    return out + [(d, h) for d in args.delays if d > 0 for h in args.handovers]


def evaluate_row(run, delay: int, handover: str, args) -> dict:
    inference = run_inference(run)
    if delay:
        inference = dataclasses.replace(inference, delay=delay, handover=handover)
    cfg = run.policy.cfg
    thresholds, _ = calibration.resolve_thresholds(inference, cfg.chunk.num_freqs,
                                                   calibration.read_calibration(run.run_dir))
    t0 = time.perf_counter()
    ev = make_evaluator(run, inference, max_steps=args.max_steps)
    res = ev.evaluate(run.policy.params, run.policy.normalizer, args.episodes, eval_key(args.eval_seed), thresholds)
    s = result_record(res)
    steps = s["mean_steps_success"]
    return {"success_rate": s["success_rate"], "mean_steps_success": steps if np.isfinite(steps) else None,
            "mean_steps": s["mean_steps"], "mean_decisions": s["mean_decisions"],
            "mean_actions_per_decision": s["mean_actions_per_decision"],
            "stride_fracs": {k: v for k, v in s.items() if k.startswith("stride") and k.endswith("_frac")},
            "success": s["success"], "eval_s": time.perf_counter() - t0}


def plot(rows: list[dict], path: str) -> str:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = list(dict.fromkeys(r["task"] for r in rows))
    fig, axes = plt.subplots(2, len(tasks), figsize=(5 * len(tasks), 7), squeeze=False)
    styles = {"naive": "--", "inpaint": "-"}
    for j, task in enumerate(tasks):
        for label in dict.fromkeys(r["label"] for r in rows if r["task"] == task):
            mine = [r for r in rows if r["task"] == task and r["label"] == label]
            sync = [r for r in mine if r["delay"] == 0]
            for h in ("naive", "inpaint"):
                line = sorted(sync + [r for r in mine if r["handover"] == h], key=lambda r: r["delay"])
                if len(line) < 2:
                    continue
                d = [r["delay"] for r in line]
                kw = dict(ls=styles[h], marker="o", label=f"{label}, {h}")
                axes[0, j].plot(d, [100 * r["success_rate"] for r in line], **kw)
                axes[1, j].plot(d, [np.nan if r["mean_steps_success"] is None else r["mean_steps_success"]
                                    for r in line], **kw)
        axes[0, j].set_title(task)
        axes[0, j].set_ylabel("success (%)")
        axes[1, j].set_ylabel("control steps to success")
        axes[1, j].set_xlabel("inference delay d (control steps)")
        for ax in axes[:, j]:
            ax.grid(alpha=0.3)
        axes[0, j].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def table(rows: list[dict]) -> str:
    body = [[r["task"], r["label"], r["delay"], r["handover"], 100 * r["success_rate"],
             float("nan") if r["mean_steps_success"] is None else r["mean_steps_success"], r["mean_decisions"]]
            for r in rows]
    return markdown_table(["task", "policy", "d", "hand-over", "success %", "steps (successful)", "decisions"], body)


def main(argv=None) -> dict:
    args = parse_args(argv)
    path = os.path.join(args.out_dir or os.path.join(os.path.dirname(__file__), "results"),
                        f"{NAME}_{device_kind()}.json")
    old = [] if args.fresh or not os.path.exists(path) else jsonio.load(path).get("rows", [])
    rows = {(r["task"], r["label"], r["delay"], r["handover"]): r for r in old}
    command = "python -m benchmarks.delay " + " ".join(sys.argv[1:] if argv is None else argv)

    def save():
        ordered = sorted(rows.values(), key=lambda r: (r["task"], r["label"], r["delay"], r["handover"]))
        write_results(NAME, {"command": command, "args": {k: v for k, v in vars(args).items() if k != "out_dir"},
                             "rows": ordered, "table_md": table(ordered)}, args.out_dir)
        return ordered

    runs = {k: load_run(v) for k, v in run_paths(args).items()}  # fail early on a missing run
    for (task, label), run in runs.items():
        for delay, handover in settings(args):
            ident = {"task": task, "label": label, "delay": delay, "handover": handover,
                     "run": os.path.relpath(run.run_dir), "checkpoint_step": int(run.policy.step),
                     "episodes": args.episodes, "eval_seed": args.eval_seed, "max_steps": args.max_steps}
            prev = rows.get((task, label, delay, handover))
            if prev and all(prev.get(k) == v for k, v in ident.items()):
                continue
            row = {**ident, **evaluate_row(run, delay, handover, args)}
            rows[(task, label, delay, handover)] = row
            save()
            print(f"[{task}] {label} d={delay} {handover}: success {row['success_rate']:.2f}, steps "
                  f"{row['mean_steps_success']}, decisions {row['mean_decisions']:.1f} ({row['eval_s']:.0f} s)",
                  flush=True)
    ordered = save()
    png = plot(ordered, path[:-5] + ".png")
    print(table(ordered))
    print(f"wrote {path}, {png}")
    return {"rows": ordered, "png": png}


if __name__ == "__main__":
    main()
