"""Reproduce the paper's experiment tables on the MJX tasks: ``python -m experiments.paper TABLE --budget B``.

Tables (sub-commands), each trained with ``hipolicy_jax.runs.train`` and evaluated on the same episodes per seed:

- ``main``: DP vs DP+HiPolicy per task, precise / non-precise tasks apart (``envs.TASK_PRECISE``); with
  ``--obs-types state pointcloud`` also DP3 vs DP3+HiPolicy (point-cloud encoder, sample prediction).
- ``ablation``: HiPolicy with hierarchical / low-only / high-only observation conditions, without fusion, and
  without the hierarchy (one stride, i.e. DP).
- ``execution``: success, steps to success and decisions of DP executing whole chunks, with temporal ensembling
  (DP+TE) and with adaptive action chunking (DP+AAC), and of DP+HiPolicy always at stride 1 (w/o EG) and
  entropy-guided (HiPolicy) — the same trained runs, evaluated with different execution strategies.
- ``thresholds``: entropy-guided execution with thresholds at several percentile pairs of held-out demo entropies.
- ``hparams``: L_h, L_c and M around the defaults (3, 8, 3).
- ``speedup``: HiPolicy against DemoSpeedup (amendment 5): DP, DP on DemoSpeedup-accelerated demos, DP+AAC,
  DP+HiPolicy and HiPolicy on the accelerated demos, at 8,000 training steps; each task's accelerated buffer is made
  from its proxy (the DP network of seed 0) before its runs (``hipolicy_jax/campaigns/speedup.py``).
- ``pilot``: the protocol's DP-only pilot that picks each task's low-data regime (``--regime rlow``).
- ``campaign``: all of the protocol's tables (results/PROTOCOL.md) — every run and evaluation under one progress
  bar with its ETA, then every table from the records and ``findings.md``: each paired comparison of HiPolicy
  with a baseline (DP, DP3, DP+TE, DP+AAC) per task and on average, with its verdict (wins / ties / loses).
  ``--executor slurm`` (``--slurm-*``, ``--cluster-*``) runs each run as one job of a SLURM job array through
  submitit and waits for them (``--executor local``: the same jobs as local processes).

Budgets: ``smoke`` (tiny model, a dozen steps: checks the pipeline in a couple of minutes), ``cpu`` (CPU model,
2000 steps: about 10 minutes of training per run on 2 cores), ``gpu`` (paper-size model, N=100, 100 DDPM steps).
Runs go to ``--runs/<budget>/<task>/<obs>/<variant>/seed<k>`` and are shared between tables (DP, HiPolicy); an
existing finished run is reused and an unfinished one resumed. Every evaluation is kept in the run's record,
``--records/<budget>/<task>/<obs>/<variant>/seed<k>.json`` (committed: configs, calibration, per-episode outcomes),
so ``--from-records`` rebuilds a table from git alone and a campaign continues on a new machine without retraining
what is recorded. Outputs: ``--results/<table>.md`` (mean over seeds with its 95 % t interval over seeds, paired
comparisons, the command, seeds and cost at the top), ``<table>.png`` and ``<table>.json`` (every record).
The protocol of the campaign these tables belong to is ``results/PROTOCOL.md``.

    python -m experiments.paper execution --budget smoke --tasks press_button --seeds 0
    python -m experiments.paper pilot --budget cpu
    python -m experiments.paper main --budget cpu --regime rlow --seeds 0 1 2
    python -m experiments.paper main --from-records
    python -m experiments.paper speedup --plan
    python -m experiments.paper campaign --executor slurm --slurm-partition cpu --cluster-time-min 240
"""

from __future__ import annotations

from hipolicy_jax.campaigns import speedup, tables
from hipolicy_jax.runs.cli import run_table_cli, table_cli

SUBCOMMANDS = {**tables.SUBCOMMANDS, speedup.SpeedupArgs.TABLE: speedup.SpeedupArgs}


def build(args) -> str:
    """The table's builder: amendment 5's (``campaigns.speedup``) or one of ``campaigns.tables``."""
    return speedup.speedup_table(args) if isinstance(args, speedup.SpeedupArgs) else tables.build(args)


# parse_args(argv) -> the table's args; main(args) -> builds and prints it, returns its markdown file's path
parse_args, main = table_cli(SUBCOMMANDS, build, __doc__, "paper")

if __name__ == "__main__":
    run_table_cli(parse_args, main)
