"""The Meta-World benchmark (results/metaworld/PROTOCOL.md): ``python -m experiments.metaworld TABLE``.

Tables (sub-commands), each training with ``hipolicy_jax.runs.train`` on scripted-expert demos that the bridge
collects in its own venv (``bash scripts/setup_metaworld.sh``), and evaluating through the project's policy server
with the bridge's env side (``metaworld_bridge.evaluate``, openpi's client):

- ``pilot``: DP (state, seed 0) trained 8000 steps on basketball and assembly, checkpoints at 1000 / 2000 / 4000 /
  8000 evaluated on 100 episodes; chooses the training length T → ``results/metaworld/pilot.md``.
- ``main``: DP, DP+HiPolicy (state) and DP3, DP3+HiPolicy (512-point clouds), 3 seeds × 100 episodes per task, in the
  protocol's order, then ``results/metaworld/main.md`` / ``.png`` / ``.json`` from the records: success with paired
  comparisons, and DP3's metric (mean of the 5 best of 10 periodic 20-episode evaluations) beside DP3's published
  numbers. ``--until HH:MM`` starts only the jobs estimated to end before then; ``--plan`` writes what is left;
  ``--from-records`` only rebuilds the table.
- ``pilot2`` (amendment 2): DP (state, seed 0) on bin-picking and hand-insert (absolute targets), T_task steps at batch
  128, checkpoints at T/4, T/2, 3T/4, T evaluated under ``waypoint`` (500-step limit); the plateau rule's f, the
  measured rates and the budget rule → ``results/metaworld/amendment2/pilot2.md``, ``pilot_choice.json``,
  ``t_task.json``.
- ``amendment2``: DP and DP+HiPolicy (state, seeds 0, 1, 2, f·T_task steps at batch 128) on the arm's tasks
  (``--arm a``: absolute targets; ``--arm b``: summed deltas), each network evaluated under ``waypoint`` at
  closed-loop thresholds and the secondary settings → ``results/metaworld/amendment2/amendment2.md``; ``--plan``,
  ``--until``, ``--from-records`` as ``main``.

Runs go to ``--runs/metaworld/metaworld_<task>/<obs>/<variant>/seed<k>``, records (committed) to
``--records/metaworld/...``; a campaign continues where its records end.

    python -m experiments.metaworld pilot
    python -m experiments.metaworld main --until 18:00
    python -m experiments.metaworld main --from-records
    python -m experiments.metaworld pilot2
    python -m experiments.metaworld amendment2 --plan
    python -m experiments.metaworld amendment2 --until 18:00
"""

from __future__ import annotations

from hipolicy_jax.campaigns import metaworld, metaworld_amendment2
from hipolicy_jax.runs.cli import run_table_cli, table_cli

SUBCOMMANDS = {**metaworld.SUBCOMMANDS, **metaworld_amendment2.SUBCOMMANDS}
BUILDERS = {**metaworld.BUILDERS, **metaworld_amendment2.BUILDERS}


def build(args) -> str:
    return BUILDERS[type(args).TABLE](args)


# parse_args(argv) -> the table's args; main(args) -> builds and prints it, returns its markdown file's path
parse_args, main = table_cli(SUBCOMMANDS, build, __doc__, "metaworld")

if __name__ == "__main__":
    run_table_cli(parse_args, main)
