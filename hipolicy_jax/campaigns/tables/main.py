"""The main table (results/PROTOCOL.md (a)): DP vs DP+HiPolicy per task, precise / non-precise tasks apart, and
with ``--obs-types state pointcloud`` DP3 vs DP3+HiPolicy → ``<results>/main[_rlow].{md,json,png}``."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

from hipolicy_jax.envs import TASK_PRECISE
from hipolicy_jax.campaigns.budgets import DP
from hipolicy_jax.campaigns.campaign import Column
from hipolicy_jax.campaigns.report import markdown_table
from hipolicy_jax.campaigns.tables import common
from hipolicy_jax.campaigns.tables.common import (PAIRED_NOTE, ObsName, PaperArgs, demo_steps, grouped_rows,
                                                  success_by_task_figure, train_args, write_results)


BASELINE_NAME = {"state": "DP", "image": "DP (image)", "pointcloud": "DP3"}


@dataclasses.dataclass(frozen=True)
class MainArgs(PaperArgs):
    """DP vs DP+HiPolicy (and DP3 vs DP3+HiPolicy with --obs-types state pointcloud), precise / non-precise."""

    TABLE: ClassVar[str] = "main"

    obs_types: tuple[ObsName, ...] | None = None  # default: state; on the gpu budget state and pointcloud

    def resolved_obs_types(self) -> tuple[str, ...]:
        if self.obs_types is not None:
            return tuple(self.obs_types)
        return ("state", "pointcloud") if self.budget == "gpu" else ("state",)


def main_columns(args: MainArgs) -> list[Column]:
    columns = []
    for obs in args.resolved_obs_types():
        base = BASELINE_NAME[obs]
        columns += [Column(base, obs, DP), Column(f"{base}+HiPolicy", obs)]
    return columns


def main_table(args: MainArgs) -> str:
    columns = main_columns(args)
    obs_types = args.resolved_obs_types()
    records = common.collect(args, columns)
    labels = [c.label for c in columns]
    rel = {f"{BASELINE_NAME[o]}+HiPolicy": BASELINE_NAME[o] for o in obs_types}
    pairs = [(f"{BASELINE_NAME[o]}+HiPolicy", BASELINE_NAME[o]) for o in obs_types]
    rows = grouped_rows(args, records, labels, rel_to=rel, paired=pairs,
                        extra=lambda t: ["yes" if TASK_PRECISE[t] else "no", demo_steps(args, t, obs_types)])
    table = markdown_table(["Task", "Precise", "Demo steps", *labels, *(f"{a} − {b} (points)" for a, b in pairs)],
                           rows)
    notes = ["Success rate (%) with entropy-guided execution, thresholds calibrated on held-out demos "
             "(10th / 70th percentiles); relative gain over the baseline in the average rows.",
             PAIRED_NOTE,
             "DP = one stride (single-frequency Diffusion Policy); DP3 = point-cloud encoder, sample prediction."]
    if "pointcloud" in obs_types:
        pc = train_args(args, args.tasks[0], "pointcloud", (), args.seeds[0]).policy.encoder
        notes.append(f"DP3 columns: {pc.num_points} points (xyz{'+rgb' if pc.point_dims == 6 else ''}) from one "
                     f"ray-cast camera plus proprioception (the first {pc.state_dims} state features: TCP xyz, "
                     "gripper); the DP columns read the full state (proprioception and object poses).")

    figure = success_by_task_figure(args, records, labels, "main results")
    return write_results(args, "Main results: success rate (%)", notes, table, records, figure)
