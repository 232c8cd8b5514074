"""Calibrate entropy thresholds: ``python -m experiments.calibrate --checkpoint RUN_DIR``.

``--inference.percentiles 10 70`` (the default for M = 3) sets the percentiles. ``--rule success --source
rollouts`` instead keeps the most aggressive of a ladder of percentiles whose closed-loop success on calibration
episodes is within ``--margin`` of stride 1's on the same episodes (every candidate's success and stride mix go into
the record and are printed).

Measures the trained policy's Gaussian action entropy (N samples per window) either on the held-out demos
(``--source demos``: the validation episodes of the run's demo buffer, split as in training) or on its own
closed-loop rollouts executed at the highest frequency (``--source rollouts``: every replan's entropy). The M+1
thresholds are (−inf, the M−1 percentiles, +inf): the paper took the 10th and 70th percentiles for M = 3 (the
default). The inference settings (N, sampler, steps, percentiles, windows) default to the run's ``inference.json``,
so with ``--source demos`` this reproduces the calibration ``experiments.train`` wrote (same windows, same key).

Writes ``RUN_DIR/calibration.json`` (read by ``experiments.evaluate``; ``--out`` to write elsewhere) and a histogram
PNG next to it (``calibration.png``), and prints a text histogram with the thresholds marked.

An external task's run (``metaworld:<task>``) rolls out through the policy server and its bridge in the bridge's
venv (``hipolicy_jax.runs.external.calibration_rollout``): calibration episodes from initial-state seeds
``3000000 + 1000 seed + i``, disjoint from the campaign's evaluation, each pass kept in the run dir
(``external_eval/``), so a repeated calibration runs no episode again.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.evaluation.plots import text_histogram
from hipolicy_jax.runs.calibrate import calibrate_run
from hipolicy_jax.runs.cli import prepare_process, run_main
from hipolicy_jax.runs.store import load_run


@dataclasses.dataclass(frozen=True)
class CalibrateArgs:
    checkpoint: str  # run dir (holding checkpoints/) or its checkpoints/ dir
    step: int | None = None  # checkpoint step (default: the latest)
    source: Literal["demos", "rollouts"] = "demos"
    inference: InferenceConfig = InferenceConfig()  # default: the run's inference.json
    rule: Literal["percentiles", "success"] = "percentiles"  # success: the success-constrained rule (rollouts)
    margin: float = 0.05  # rule success: the success-rate points a candidate may lose to stride 1
    episodes: int = 20  # rollouts: episodes
    seed: int | None = None  # default: the run's training seed
    out: str = ""  # default RUN_DIR/calibration.json (the histogram goes next to it as .png)
    bins: int = 24


def main(args: CalibrateArgs) -> dict:
    run = load_run(args.checkpoint, args.step)
    record = calibrate_run(run, args.inference, args.source, episodes=args.episodes, seed=args.seed, out=args.out,
                           bins=args.bins, rule=args.rule, margin=args.margin)
    if args.rule == "success":
        base = record["baseline"]
        where = (f" (initial states {record['first_seed']}..{record['first_seed'] + args.episodes - 1})"
                 if "first_seed" in record else "")
        print(f"stride 1 on {args.episodes} calibration episodes{where}: success {base['success_rate']:.2f}, "
              f"{base['mean_steps']:.1f} control steps; candidates (percentiles: success, steps, intended -> "
              f"achieved stride mix):")
        for i, c in enumerate(record["candidates"]):
            mix = ", ".join(f"{s}: {c['intended_mix'][s]:.2f}->{c['achieved_mix'][s]:.2f}" for s in c["intended_mix"])
            mark = "  <- chosen" if i == record["chosen"] else ""
            print(f"  {c['percentiles']}: {c['success_rate']:.2f}, {c['mean_steps']:.1f} steps, {{{mix}}}{mark}")
    inf = record["inference"]
    print(f"{run.task} @ step {run.policy.step}: {record['num_windows']} entropies from {args.source} "
          f"(N={inf['num_samples']}, sampler {inf['sampler']}, steps {inf['num_steps']})")
    print(text_histogram(record["entropies"], record["thresholds"], args.bins))
    print(f"thresholds {[round(float(t), 4) for t in record['thresholds']]} (percentiles {record['percentiles']}) "
          f"-> {record['path']}, {record['plot']}")
    return record


if __name__ == "__main__":
    prepare_process()
    run_main(CalibrateArgs, main, __doc__)
