"""Amendment 5 of the MJX protocol (``results/PROTOCOL.md``, "Amendment 5"): HiPolicy against DemoSpeedup, the
field's offline speed-up method, on the same tasks, budget and initial states, and the two stacked.

Five methods per (task, seed), every network trained ``steps`` steps on the task's 100 demos (state observations):

- ``DP``: one stride (the training-budget table's 8,000-step DP network);
- ``DP (DemoSpeedup)``: one stride, trained on the DemoSpeedup-accelerated demos with half the chunk (L_c = 4,
  upstream's "geometrical consistency" rule: DP's 48 → 24);
- ``DP+AAC``: the DP network executed with adaptive action chunking (no retraining);
- ``DP+HiPolicy``: strides 1/2/3, entropy-guided (the budget table's 8,000-step HiPolicy network);
- ``HiPolicy (DemoSpeedup)``: strides 1/2/3 on the accelerated demos, L_c = 4 (the two ideas stacked).

The accelerated buffer of a task (``budgets.speedup_data_path``: ``data/<task>_state_100_speedup.zarr``) is made once
by ``ensure_accelerated`` from ONE proxy, the DP network of seed 0 (DemoSpeedup trains one proxy on the normal-speed
demos), with ``SPEEDUP`` (the authors' defaults, the 1 s casual prefix at our 10 Hz, and the bandwidth ladder), and
shared by every seed; what the stage did goes to ``<results>/speedup/stage/<task>.json`` (committed: the buffer itself
is not) and its entropy plot beside it. The proxy's training and the stage's time count in the DemoSpeedup methods'
cost.

Every method is evaluated under ``rate`` (primary) and ``waypoint`` (secondary) on the seed's 100 initial states
(``eval_key(seed)``). The table (``<results>/speedup.md`` / ``.json`` / ``.png``) comes from the records alone:
success with the paired difference to DP, the decisions / actions / control steps relative to DP on the initial
states both solved, HiPolicy and DemoSpeedup head to head, and each method's training cost; the reading rule
(``reading``) answers which method is fastest at DP's success. Networks of the shared cells trained before the
fidelity fixes (``PRE_FIX``) are never read: their cells stay missing until retrained.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from typing import ClassVar, Literal, NamedTuple

import numpy as np

from hipolicy_jax.campaigns.budgets import BUDGETS, DP, speedup_data_path
from hipolicy_jax.campaigns.campaign import Column, CostModel, Job, work_off
from hipolicy_jax.campaigns.metaworld import pending_lines
from hipolicy_jax.campaigns.report import (EPISODE_COUNTS, ci, cpu_s, interval_text, markdown_table, paired,
                                           paired_cell, relative_count_difference)
from hipolicy_jax.campaigns.tables import PaperArgs, TaskName, campaign, table_record, write_results
from hipolicy_jax.data.replay_buffer import collection_lock

from hipolicy_jax.evaluation import stats
from hipolicy_jax.runs import records as rec_lib
from hipolicy_jax.runs.lock import CAMPAIGN_LOCK_FILE, RunLock, RunLockedError
from hipolicy_jax.runs.store import read_json, write_json
from hipolicy_jax.runs.train import cpu_seconds, ensure_trained, prepare_out_dir
from hipolicy_jax.speedup.config import SpeedupConfig

TASKS = ("press_button", "stack_cubes", "latch_door")
STEPS = 8000
# The stage's settings (the amendment): the authors' defaults but for the casual prefix (50 frames = 1 s at their
# 50 Hz; ours run at 10 Hz) and a bandwidth ladder (the first at most half of whose frames saturate)
SPEEDUP = SpeedupConfig(casual_prefix=10, bandwidth_ladder=(0.005, 0.01, 0.02, 0.05, 0.1, 0.2))
SPEEDUP_CHUNK = (("chunk.chunk_len", 4),)  # half the chunk on the accelerated demos (upstream)
PROXY_SEED = 0  # the proxy is the DP network of this seed
STAGE_SEED = 0  # the stage's sampler key
SEMANTICS = ("rate", "waypoint")  # primary, secondary
BUDGET_HOURS = 25.0
KEEP_BOUND = -0.10  # the reading rule: a method keeps DP's success when the average's lower end is above this
PRE_FIX = "pre_fix_networks.json"  # beside the table: the shared cells' networks from before the fidelity fixes


class Method(NamedTuple):
    """One compared method: its label, the network's config changes, its execution strategy and whether its
    network trains on the accelerated demos."""

    label: str
    changes: tuple
    execution: str = "chunk"
    speedup: bool = False


DP_LABEL, DPS_LABEL, AAC_LABEL, HIP_LABEL, HIPS_LABEL = ("DP", "DP (DemoSpeedup)", "DP+AAC", "DP+HiPolicy",
                                                         "HiPolicy (DemoSpeedup)")
METHODS = (Method(DP_LABEL, DP), Method(DPS_LABEL, tuple(sorted(DP + SPEEDUP_CHUNK)), speedup=True),
           Method(AAC_LABEL, DP, execution="aac"), Method(HIP_LABEL, ()),
           Method(HIPS_LABEL, SPEEDUP_CHUNK, speedup=True))
# head to head (new, base): which idea is faster, and does stacking help
HEAD_TO_HEAD = ((HIP_LABEL, DPS_LABEL), (HIPS_LABEL, DPS_LABEL), (HIPS_LABEL, HIP_LABEL))


def label(method: Method, semantics: str) -> str:
    """The column label: the method's, with ``(waypoint)`` under the secondary semantics."""
    return method.label if semantics == "rate" else f"{method.label} (waypoint)"


def column(method: Method, semantics: str) -> Column:
    return Column(label(method, semantics), "state", method.changes, execution=method.execution,
                  semantics=semantics)


@dataclasses.dataclass(frozen=True)
class SpeedupArgs(PaperArgs):
    """HiPolicy against DemoSpeedup (results/PROTOCOL.md amendment 5): run what is pending, then the table from the
    records (``--from-records``: the table alone; ``--plan``: only what is left, with its estimated cost)."""

    TABLE: ClassVar[str] = "speedup"
    tasks: tuple[TaskName, ...] = TASKS
    steps: int = STEPS  # training steps of every network
    semantics: tuple[Literal["rate", "waypoint"], ...] = SEMANTICS  # the first is the primary
    plan: bool = False  # write <results>/speedup_plan.md (what is left, its cost) and stop
    shard: tuple[int, int] = (0, 1)  # K N: this process works on the K-th of N interleaved shards of the runs
    until: str = ""  # skip jobs that would end after this time (HH:MM or an ISO date-time)
    tables: bool = True  # write the table after the runs (--no-tables: only the plan)

    def __post_init__(self):
        if self.regime != "r100" or self.baseline_seeds:
            raise ValueError(f"speedup: the amendment trains on 100 demos with the protocol's seeds alone; --regime "
                             f"must be r100 and --baseline-seeds empty, got {self.regime} and "
                             f"{list(self.baseline_seeds)}")
        if not self.semantics:
            raise ValueError("semantics: at least one (the first is the primary), got none")


def run_changes(args: SpeedupArgs, method: Method) -> dict:
    """The run-level changes of a method's runs: the amendment's training steps, and ``speedup`` for the methods
    trained on the accelerated demos."""
    changes = {} if args.steps == BUDGETS[args.budget].train.num_steps else {"train.num_steps": args.steps}
    return {**changes, "speedup": True} if method.speedup else changes


def jobs(args: SpeedupArgs) -> list[Job]:
    """Task by task: the proxy's network (DP) first, then DP+HiPolicy, then the two on the accelerated demos; a
    network's evaluations that no earlier table made come first (DP+AAC before DP, the secondary semantics before
    the primary), so that a shared network from before the fidelity fixes is retrained before any of its recorded
    evaluations could be reused (``PRE_FIX``). Seeds ascending inside each (method, semantics)."""
    order = (METHODS[2], METHODS[0], METHODS[3], METHODS[1], METHODS[4])  # AAC, DP, DP+HiPolicy, the two stacked
    out = []
    for task in args.tasks:
        for method in order:
            changes = tuple(sorted(run_changes(args, method).items()))
            for sem in reversed(args.semantics):
                out += [Job(task, column(method, sem), seed, changes) for seed in args.seeds]
    return out


def run_of(args: SpeedupArgs):
    camp = campaign(args)
    return lambda j: camp.run_config(j.task, j.col, j.seed, dict(j.changes)).out_dir()


# ------------------------------------------------------------------------------------------ the shared networks


def pre_fix_networks(args: SpeedupArgs) -> list[dict]:
    """The fingerprints of ``<results>/speedup/pre_fix_networks.json`` (none when the file is absent)."""
    path = os.path.join(args.results, "speedup", PRE_FIX)
    if not os.path.exists(path):
        return []
    return [n for nets in read_json(path)["networks"].values() for n in nets]


def is_pre_fix(net: dict | None, old: list[dict]) -> bool:
    return bool(net) and any(rec_lib.same_network(net, o) for o in old)


# ------------------------------------------------------------------------------------------------ the stage


def stage_path(args: SpeedupArgs, task: str) -> str:
    return os.path.join(args.results, "speedup", "stage", f"{task}.json")


def kept_sha256(kept: list[list[int]]) -> str:
    """A fingerprint of the frames every episode keeps (what the accelerated buffer is made of)."""
    return hashlib.sha256(json.dumps(kept).encode()).hexdigest()


def stage_summary(record: dict, seconds: float, cpu_seconds_: float, proxy_net: dict) -> dict:
    """The committed summary of one stage (``stage.speedup_demos``'s record less the per-frame lists)."""
    lengths, new = np.asarray(record["original_lengths"]), np.asarray(record["new_lengths"])
    precise = sum(e - s for segs in record["segments"] for s, e, lab, _ in segs if lab == 0)  # [start, end, label, rate]
    return {"task": record["task"], "proxy": os.path.relpath(record["proxy"]), "proxy_step": record["proxy_step"],
            "proxy_network": proxy_net, "config": record["config"], "sampler": record["sampler"],
            "seed": record["seed"], "bandwidth": record["bandwidth"],
            "saturated_by_bandwidth": record["saturated_by_bandwidth"],
            "saturated_fraction": record["saturated_fraction"],
            "original_frames": record["original_frames"], "new_frames": record["new_frames"],
            "speedup": record["original_frames"] / record["new_frames"],
            "mean_original_length": float(lengths.mean()), "mean_new_length": float(new.mean()),
            "precise_fraction": precise / record["original_frames"],
            "kept_sha256": kept_sha256(record["kept"]), "stage_s": seconds, "stage_cpu_s": cpu_seconds_}


def _with_lock_retries(fn, wait_s: float = 30.0, tries: int = 240):
    """``fn()``, waiting while another campaign process holds the run (``RunLockedError``)."""
    for _ in range(tries - 1):
        try:
            return fn()
        except RunLockedError:
            time.sleep(wait_s)
    return fn()


def ensure_accelerated(args: SpeedupArgs, task: str) -> str:
    """The task's accelerated buffer, made when missing: the proxy (DP, seed ``PROXY_SEED``) trained and evaluated
    first (its AAC evaluation: a new one, so a network from before the fidelity fixes is replaced), then the stage
    on the plain demos; its summary to ``stage_path`` and its plot beside it. One process makes it; the others
    wait on its lock. A proxy from before the fidelity fixes, or a remade buffer that keeps other frames than the
    committed summary says, is refused / reported in one line."""
    from hipolicy_jax.speedup.plot import plot_episode
    from hipolicy_jax.speedup.stage import speedup_demos

    camp = campaign(args)
    dp, aac = METHODS[0], METHODS[2]
    changes = run_changes(args, dp)
    cfg = camp.run_config(task, column(dp, "rate"), PROXY_SEED, changes)
    out = speedup_data_path(cfg.data_path())
    if os.path.exists(out):
        return out
    with collection_lock(out, "speedup campaign"):
        if os.path.exists(out):
            return out
        _with_lock_retries(lambda: camp.evaluate(task, column(aac, "rate"), PROXY_SEED, changes))
        with RunLock(prepare_out_dir(cfg.out_dir()), CAMPAIGN_LOCK_FILE, "campaign process",
                     "another shard is training or evaluating it; this one waits"):
            run = ensure_trained(cfg)
        net = rec_lib.network(run.policy.params, None)
        if is_pre_fix(net, pre_fix_networks(args)):
            raise ValueError(f"{cfg.out_dir()}: the proxy is a network trained before the fidelity fixes "
                             f"({os.path.join(args.results, 'speedup', PRE_FIX)}); delete that run dir to retrain it")
        t0, c0 = time.perf_counter(), cpu_seconds()
        result = speedup_demos(cfg.data_path(), run, out, SPEEDUP, seed=STAGE_SEED)
        summary = stage_summary(result.record, time.perf_counter() - t0, cpu_seconds() - c0, net)
        path = stage_path(args, task)
        if os.path.exists(path):
            before = read_json(path)
            if before.get("kept_sha256") != summary["kept_sha256"]:
                print(f"[speedup] {out}: remade from a retrained proxy, it keeps other frames than {path} recorded; "
                      f"the runs trained on the earlier buffer stay in the table, and the summary lists both",
                      flush=True)
                summary["earlier"] = [*before.get("earlier", []), {k: v for k, v in before.items() if k != "earlier"}]
        write_json(path, summary)
        sl = result.source.episode_slice(0)
        plot_episode(result.entropy[sl], result.record["segments"][0], np.asarray(result.record["kept"][0]),
                     path[:-len(".json")] + "_entropy.png",
                     title=f"{task} demo 0: {sl.stop - sl.start} -> {result.record['new_lengths'][0]} frames "
                           f"(DemoSpeedup, N={SPEEDUP.num_samples}, bandwidth {summary['bandwidth']:g})")
        print(f"[speedup] {task}: {summary['original_frames']} -> {summary['new_frames']} frames "
              f"(x{summary['speedup']:.2f}), bandwidth {summary['bandwidth']:g}, "
              f"{100 * summary['precise_fraction']:.0f} % of frames precise -> {out}", flush=True)
        return out


# ------------------------------------------------------------------------------------------------ the table


def table_records(args: SpeedupArgs, all_jobs: list[Job]) -> tuple[list[dict], int, int]:
    """The jobs' recorded evaluations as table rows, how many jobs have none, and how many were left out as
    evaluations of a network from before the fidelity fixes."""
    reader = campaign(dataclasses.replace(args, from_records=True))
    old = pre_fix_networks(args)
    records, missing, stale = [], 0, 0
    for task, col, seed, changes in all_jobs:
        ev = reader.evaluate(task, col, seed, dict(changes))
        if ev is None:
            missing += 1
            continue
        if is_pre_fix(ev.get("network"), old):
            stale += 1
            continue
        records.append(table_record(reader, task, col, seed, dict(changes), ev))
    return records, missing, stale


def reading(success: stats.Estimate, steps: stats.Estimate, bound: float = KEEP_BOUND) -> str:
    """The amendment's reading of a method against DP, averaged over the tasks: it keeps DP's success when the
    paired difference's lower end is above ``bound``; it is faster when its relative control steps' interval lies
    below 0."""
    if not (np.isfinite(success.low) and np.isfinite(steps.high)):
        return "–"
    keeps = success.low > bound
    faster = steps.high < 0
    slower = steps.low > 0
    speed = "faster" if faster else ("slower" if slower else "no measurable difference in control steps")
    return f"{'keeps' if keeps else 'does not keep'} DP's success; {speed}"


def success_difference(records: list[dict], seeds, tasks, new: str, base: str) -> stats.Estimate:
    """``new`` − ``base`` success pooled over ``tasks`` (``report.paired``'s t interval); NaN while a task has no
    pair."""
    c = paired(records, seeds, tasks, new, base)
    return stats.NAN if c is None else c.diff


def training_hours(records: list[dict], method: str, stages: dict[str, dict], proxy: dict[str, float]) -> str:
    """A method's mean training CPU-hours per network; a DemoSpeedup method's adds its share of the proxy's training
    and the stage (one per task, shared by its seeds and both DemoSpeedup methods: counted in full for each)."""
    rows = [r for r in records if r["column"] == method]
    own = [cpu_s(r["training_s"], r.get("training_cores"), r.get("training_cpu_s")) for r in rows
           if r.get("training_s")]
    if not own:
        return "–"
    text = f"{np.mean(own) / 3600:.2f}"
    if method in (DPS_LABEL, HIPS_LABEL):
        tasks = sorted({r["task"] for r in rows})
        extra = [proxy.get(t, 0.0) + stages.get(t, {}).get("stage_cpu_s", 0.0) for t in tasks]
        text += f" + {np.mean(extra) / 3600:.2f} (proxy and stage, per task)"
    return text


def build_table(args: SpeedupArgs, records: list[dict], n_jobs: int, missing: int, stale: int) -> str:
    tasks, seeds = list(args.tasks), tuple(args.seeds)
    groups = [([t], t) for t in tasks] + ([(tasks, "**Average**")] if len(tasks) > 1 else [])
    labels = [m.label for m in METHODS]
    sections = []
    for sem in args.semantics:
        lab = {m.label: label(m, sem) for m in METHODS}
        title = "primary" if sem == args.semantics[0] else "secondary"
        rows = [[name, *(ci(records, "success_rate", seeds, ts, 100.0, column=lab[m]) for m in labels),
                 *(paired_cell(records, seeds, ts, lab[m], lab[DP_LABEL]) for m in labels[1:])]
                for ts, name in groups]
        header = ["Task", *(f"{m} SR (%)" for m in labels), *(f"{m} − DP (points)" for m in labels[1:])]
        sections += [f"## Success under `{sem}` ({title})", "", markdown_table(header, rows), ""]
        rows = []
        for ts, name in groups:
            for m in labels[1:]:
                rows.append([name, m, ci(records, "mean_steps_success", seeds, ts, column=lab[m]),
                             *(interval_text(relative_count_difference(records, seeds, ts, lab[m], lab[DP_LABEL],
                                                                       count), 100.0, signed=True)
                               for count in EPISODE_COUNTS)])
            rows.append([name, DP_LABEL, ci(records, "mean_steps_success", seeds, ts, column=lab[DP_LABEL]),
                         "", "", ""])
        header = ["Task", "Method", "Control steps (successful)",
                  *(f"{name} vs DP (%)" for name in ("Decisions", "Actions", "Control steps"))]
        sections += [f"### Speed against DP under `{sem}`", "", markdown_table(header, rows), ""]
        rows = [[name, f"{new} vs {base}", paired_cell(records, seeds, ts, lab[new], lab[base]),
                 interval_text(relative_count_difference(records, seeds, ts, lab[new], lab[base], "steps"), 100.0,
                               signed=True)]
                for new, base in HEAD_TO_HEAD for ts, name in groups]
        sections += [f"### Head to head under `{sem}`", "",
                     markdown_table(["Task", "Comparison", "Success difference (points)",
                                     "Control steps (%, shared successes)"], rows), ""]
        if sem == args.semantics[0] and len(tasks) > 1:
            rows = [[m, reading(success_difference(records, seeds, tasks, lab[m], lab[DP_LABEL]),
                                relative_count_difference(records, seeds, tasks, lab[m], lab[DP_LABEL], "steps"))]
                    for m in labels[1:]]
            sections += [f"### Reading (amendment 5's rule, over the {len(tasks)} tasks)", "",
                         markdown_table(["Method", "Against DP"], rows), ""]
    stages = {t: read_json(stage_path(args, t)) for t in tasks if os.path.exists(stage_path(args, t))}
    proxy = {r["task"]: cpu_s(r["training_s"], r.get("training_cores"), r.get("training_cpu_s")) for r in records
             if r["column"] == DP_LABEL and r["seed"] == PROXY_SEED and r.get("training_s")}
    rows = [[t, f"{s['original_frames']:,} → {s['new_frames']:,} (x{s['speedup']:.2f})",
             f"{s['mean_original_length']:.1f} → {s['mean_new_length']:.1f}", f"{100 * s['precise_fraction']:.0f}",
             f"{s['bandwidth']:g}", f"{100 * s['saturated_fraction']:.0f}", f"{s['stage_cpu_s'] / 60:.1f}"]
            for t, s in stages.items()]
    sections += ["## The accelerated demos", "",
                 markdown_table(["Task", "Frames", "Frames per demo", "Precise frames (%)", "Bandwidth",
                                 "Frames at the ceiling (%)", "Stage (CPU-min)"], rows) if rows else "(none made yet)",
                 "", "## Training cost (CPU-hours per network)", "",
                 markdown_table(["Method", "Training"],
                                [[m, training_hours(records, m, stages, proxy)] for m in labels]), ""]
    interim = (f"**Interim**: {missing} of {n_jobs} evaluations have no record yet"
               + (f", {stale} are of networks from before the fidelity fixes (left out until retrained)"
                  if stale else "") + "; the cells say what the records hold so far.") if missing or stale else None
    notes = [f"Every network: state, 100 demos, {args.steps:,} training steps; DemoSpeedup's on the task's "
             f"accelerated demos (one proxy: DP seed {PROXY_SEED}; N = {SPEEDUP.num_samples}, casual prefix "
             f"{SPEEDUP.casual_prefix} frames, rates {SPEEDUP.precise_rate} / {SPEEDUP.casual_rate}, the bandwidth "
             f"ladder) with half the chunk (L_c = 4). HiPolicy columns: entropy-guided at each run's calibrated "
             f"thresholds; DP+AAC: the DP network with adaptive action chunking.",
             "SR: success rate. Differences: per seed, the mean per-episode difference on the shared initial states; "
             "mean over seeds with its 95 % t interval (average rows: Welch over the tasks). Speed: on the initial "
             "states both networks of a seed solved, the mean count per episode relative to the other's "
             "(−40 % = 40 % fewer).",
             f"Reading rule: a method keeps DP's success when the lower end of its averaged success difference is "
             f"above {100 * KEEP_BOUND:+.0f} points; it is faster when its control steps' interval lies below 0.",
             *([interim] if interim else [])]
    return write_results(args, "HiPolicy against DemoSpeedup: success and speed at 8,000 training steps", notes,
                         "\n".join(sections).rstrip() + "\n", records)


def write_plan(args: SpeedupArgs, costs: list[dict]) -> str:
    pending = [c for c in costs if not c["done"]]
    known = [c["seconds"] for c in pending if c["seconds"] is not None]
    lines = ["# Amendment 5 (HiPolicy against DemoSpeedup): what is left", "",
             f"{len(pending)} of {len(costs)} evaluations pending, {sum(c['trains'] for c in pending)} runs to train; "
             f"the cost model's estimate {sum(known) / 3600:.1f} CPU-hours for the {len(known)} with a measured rate"
             + (f" ({len(pending) - len(known)} not yet measured)" if len(known) < len(pending) else "")
             + f"; the amendment's budget is {BUDGET_HOURS:g} CPU-hours. The accelerated buffers are made before "
               f"their runs (the stage takes minutes).", "", *pending_lines(pending, costs)]
    os.makedirs(args.results, exist_ok=True)
    path = os.path.join(args.results, "speedup_plan.md")
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")
    return path


def speedup_table(args: SpeedupArgs) -> str:
    """Run what is pending (unless ``--from-records``; ``--plan`` only writes what is left) task by task: the
    networks on the plain demos (the proxy among them), the task's accelerated buffer, then the networks trained on
    it; then write the table from the records alone."""
    all_jobs = jobs(args)
    if not args.from_records:
        from hipolicy_jax.campaigns.campaign import shard

        camp = campaign(args)
        mine = shard(all_jobs, args.shard[0], args.shard[1], run_of(args))
        costs = CostModel(args.records, args.runs).estimate(camp, mine)
        if args.plan:
            return write_plan(args, CostModel(args.records, args.runs).estimate(camp, all_jobs))
        for task in args.tasks:  # per task: the plain demos' networks, then the stage, then the accelerated ones
            plain = [c for c in costs if c["job"].task == task and not dict(c["job"].changes).get("speedup")]
            fast = [c for c in costs if c["job"].task == task and dict(c["job"].changes).get("speedup")]
            work_off(camp, plain, run_of(args), until=args.until, progress=args.progress)
            if any(not c["done"] for c in fast):
                ensure_accelerated(args, task)  # trains the proxy here if another shard has not
                work_off(camp, fast, run_of(args), until=args.until, progress=args.progress)
        if not args.tables:
            return write_plan(args, CostModel(args.records, args.runs).estimate(camp, all_jobs))
    records, missing, stale = table_records(args, all_jobs)
    return build_table(args, records, len(all_jobs), missing, stale)
