"""A campaign's runs as cluster jobs through submitit: ``python -m experiments.paper campaign --executor slurm``.

A **job** is one run of the campaign (one trained network): its training and every evaluation of it the campaign
still lacks. The runs are the campaign's own grouping: ``campaign.shard`` with one shard a run (``n`` = the number
of runs of the campaign, or of its ``--shard``), so job ``k`` does exactly what ``--shard k n`` would do, through the
same ``work_off`` (records written into the shared ``--records`` as each evaluation finishes, the run's campaign
lock, ``--until``). ``--executor slurm`` submits them as one SLURM job array (``submitit.AutoExecutor``),
``--executor local`` as local processes (``submitit.LocalExecutor``, at most ``--cluster-parallel`` at once); the
submitting process waits for them under one progress bar, then builds the tables from the records as the
in-process campaign does.

A job that dies is run again from its run's last checkpoint (a run resumes from it whenever it is run again), in
two ways, as the two kinds of death differ:

- **warned** (the time limit, a preemption that signals): SLURM sends ``USR2`` before the end (submitit's
  ``--signal``), submitit calls ``RunJob.checkpoint`` (``submitit.helpers.Checkpointable``) and requeues the same
  job (same id, up to ``TIMEOUT_REQUEUES`` times for time limits);
- **unwarned** (``SIGKILL``, out of memory, a node failure, an exception such as a ``SIGTERM`` that stopped the
  training): no code of the job runs at its end, so only the submitter can notice it: a job that ends without its
  result is submitted again, at most ``--cluster-retries`` times a run, so that a run that fails for a lasting
  reason (a bug, a bad config) stops there instead of looping. A killed attempt leaves its run's locks behind; the
  next attempt releases those that name an ended attempt of its own (``release_stale_locks``), even from another
  host.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import shutil
import socket
import sys
import time
from collections.abc import Callable

import submitit
from submitit.core.utils import FailedJobError, FailedSubmissionError, UncompletedJobError

from hipolicy_jax.campaigns.campaign import CostModel, Job, report_damaged, shard, work_off as work_off_here
from hipolicy_jax.runs.lock import CAMPAIGN_LOCK_FILE, LOCK_FILE, scheduler_job

TIMEOUT_REQUEUES = 3  # submitit's requeues of a job that reached its time limit (each resumes the run)
POLL_S = {"local": 1.0, "slurm": 30.0}  # how often the submitter looks at its jobs


def logs_dir(args) -> str:
    """``--cluster-logs``, else ``<runs>/cluster-logs``."""
    return args.cluster_logs or os.path.join(args.runs, "cluster-logs")


def sbatch_options(items: tuple[str, ...]) -> dict[str, str]:
    """``--slurm-sbatch KEY=VALUE ...`` as sbatch options (``qos=high`` → ``#SBATCH --qos=high``)."""
    options = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip("-"):
            raise ValueError(f"slurm-sbatch: expected KEY=VALUE (an sbatch option without its dashes, e.g. "
                             f"qos=high), got {item!r}")
        options[key.strip("-")] = value
    return options


def check_settings(args) -> None:
    """The cluster settings' values, each a one-line ``ValueError`` naming its flag."""
    for name, low in (("cluster_time_min", 1), ("cluster_retries", 0), ("cluster_parallel", 0),
                      ("slurm_cpus_per_task", 1), ("slurm_mem_gb", 0)):
        if getattr(args, name) < low:
            raise ValueError(f"{name.replace('_', '-')}: expected a number >= {low}, got {getattr(args, name)}")
    sbatch_options(args.slurm_sbatch)


def make_executor(args) -> submitit.AutoExecutor:
    """The submitit executor ``--executor`` names, with the job settings; one-line ``ValueError`` for settings out
    of range and for ``slurm`` where this machine cannot submit (no ``sbatch`` / ``srun``)."""
    check_settings(args)
    if args.executor == "slurm" and shutil.which("sbatch") is None:
        raise ValueError("executor: --executor slurm submits with sbatch, and there is no sbatch on the PATH here; "
                         "run the command on the cluster's login node, or pass --executor local to run the jobs "
                         "as local processes")
    # a folder a SLURM job; the local executor's jobs in one (it would also make a folder literally named %j)
    folder = os.path.join(logs_dir(args), "%j") if args.executor == "slurm" else logs_dir(args)
    try:
        executor = submitit.AutoExecutor(folder=folder, cluster=args.executor,
                                         slurm_max_num_timeout=TIMEOUT_REQUEUES,
                                         local_max_num_timeout=TIMEOUT_REQUEUES)
    except RuntimeError as e:  # submitit's SlurmExecutor: sbatch found, srun not
        raise ValueError(f"executor: --executor slurm: {e} (sbatch is on the PATH, srun is not); run the command "
                         f"on the cluster's login node, or pass --executor local") from None
    params = {"name": f"campaign-{args.budget}", "timeout_min": args.cluster_time_min,
              "cpus_per_task": args.slurm_cpus_per_task}
    if args.slurm_mem_gb:
        params["mem_gb"] = args.slurm_mem_gb
    if args.slurm_partition:
        params["slurm_partition"] = args.slurm_partition
    if args.slurm_account:
        params["slurm_account"] = args.slurm_account
    if args.slurm_sbatch:
        params["slurm_additional_parameters"] = sbatch_options(args.slurm_sbatch)
    if args.cluster_parallel:
        params["slurm_array_parallelism"] = args.cluster_parallel
    executor.update_parameters(**params)
    return executor


def submission_error(args, error: Exception) -> ValueError:
    """sbatch's refusal (submitit raises it with sbatch's stderr) as one line: a partition refused names
    ``--slurm-partition``, anything else the ``--slurm-*`` settings."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    detail = lines[-1] if lines else type(error).__name__
    if "partition" in str(error).lower():
        asked = repr(args.slurm_partition) if args.slurm_partition else "the cluster's default"
        return ValueError(f"slurm-partition: sbatch refused the job array on partition {asked} ({detail}); pass "
                          f"--slurm-partition with one that `sinfo -s` lists")
    return ValueError(f"executor: sbatch refused the job array ({detail}); check the --slurm-* settings")


def release_stale_locks(run_dir: str, ended: set[str]) -> list[str]:
    """Remove the run's locks (its training's and its campaign work's) that name a SLURM job in ``ended``: an
    earlier attempt of this run's job, which has ended (the submitter resubmits only after), or this job itself
    (a requeued job keeps its id). A job killed outright leaves its locks, and a lock from another host cannot be
    checked from here (``RunLock`` refuses it). → the removed paths."""
    removed = []
    for name in (LOCK_FILE, CAMPAIGN_LOCK_FILE):
        path = os.path.join(run_dir, name)
        try:
            with open(path) as f:
                held = json.load(f)
        except (OSError, ValueError):
            continue
        if isinstance(held, dict) and held.get("job") in ended and held.get("pid") != os.getpid():
            print(f"[cluster] {path}: left by job {held['job']} (pid {held.get('pid')} on {held.get('host')}), an "
                  f"earlier attempt of this run that has ended; released", flush=True)
            os.remove(path)
            removed.append(path)
    return removed


class RunJob(submitit.helpers.Checkpointable):
    """One cluster job: the pending work of run ``k`` of the campaign's ``n`` runs (``campaign.shard`` with one
    shard a run), which is ``run_dir``; ``ended``: the SLURM ids of this run's earlier attempts. → ``work_off``'s
    list of jobs skipped for a damaged stored file. Checkpointable: on submitit's time-limit / preemption signal the
    same job is requeued and its run resumes from its last checkpoint."""

    def __init__(self, args, k: int, n: int, run_dir: str, ended: tuple[str, ...] = ()):
        self.args, self.k, self.n, self.run_dir, self.ended = args, k, n, run_dir, tuple(ended)

    def __call__(self) -> list[tuple[str, str]]:
        from hipolicy_jax.campaigns.tables import campaign_shard
        from hipolicy_jax.runs.cli import prepare_process

        prepare_process()
        args = dataclasses.replace(self.args, progress=False)  # a log file: a line a finished evaluation, no bars
        print(f"[cluster] {time.strftime('%Y-%m-%d %H:%M:%S')} {self.run_dir} on {socket.gethostname()}"
              + (f" (job {scheduler_job()})" if scheduler_job() else ""), flush=True)
        release_stale_locks(self.run_dir, {*self.ended, *([scheduler_job()] if scheduler_job() else [])})
        camp, _, jobs, _, run_of = campaign_shard(args)
        mine = shard(jobs, self.k, self.n, run_of)
        if {run_of(j) for j in mine} != {self.run_dir}:
            raise ValueError(f"executor: the campaign's runs changed since this job was submitted (run {self.k} of "
                             f"{self.n} is no longer {self.run_dir}); run the campaign command again")
        costs = CostModel(args.records, args.runs).estimate(camp, mine)
        return work_off_here(camp, costs, run_of, until=args.until, progress=False)

    def checkpoint(self, *args, **kwargs) -> submitit.helpers.DelayedSubmission:
        print(f"[cluster] {time.strftime('%Y-%m-%d %H:%M:%S')} {self.run_dir}: time limit or preemption; requeued, "
              f"the run resumes from its last checkpoint", flush=True)
        return super().checkpoint(*args, **kwargs)


@dataclasses.dataclass
class _Attempt:
    k: int
    run_dir: str
    ended: tuple[str, ...] = ()  # the SLURM ids of the run's earlier attempts


def failure_line(job, error: Exception) -> str:
    """Why a job ended without its result, in one line: its exception's last line, else its state."""
    if isinstance(error, FailedJobError):
        trace = str(error).split("----------------------")
        lines = [line.strip() for line in (trace[1] if len(trace) > 2 else str(error)).splitlines() if line.strip()]
        return f"failed: {lines[-1] if lines else 'an error'}"
    if isinstance(error, UncompletedJobError):
        return f"ended without a result (state {job.state}: killed, out of memory or time, or its node failed)"
    return f"failed: {str(error).splitlines()[0] if str(error) else type(error).__name__}"


def work_off(args, costs: list[dict], run_of: Callable[[Job], str]) -> list[tuple[str, str]]:
    """``campaign.work_off`` through submitit: one job a run with pending work (``RunJob``) on ``args.executor``,
    waited for under one progress bar (runs done / all), a job that ends without its result submitted again up to
    ``--cluster-retries`` times. → the jobs skipped for a damaged stored file (listed at the end, as in-process);
    a run that failed every attempt is a one-line ``ValueError`` once all jobs have ended (the others are
    recorded)."""
    from tqdm.auto import tqdm

    from hipolicy_jax.runs.train import cpu_cores

    runs = list(dict.fromkeys(run_of(c["job"]) for c in costs))  # campaign.shard's order: run k is shard k of n
    pending = [_Attempt(k, r) for k, r in enumerate(runs)
               if any(not c["done"] for c in costs if run_of(c["job"]) == r)]
    if not pending:
        return []
    executor = make_executor(args)
    window = len(runs) if args.executor == "slurm" else (args.cluster_parallel or cpu_cores())
    attempts = {a.run_dir: 0 for a in pending}
    active: dict = {}  # submitit job → its _Attempt
    damaged: list[tuple[str, str]] = []
    failed: list[tuple[str, str, str]] = []  # (run, one-line reason, its log)
    bar = tqdm(total=len(pending), desc=f"campaign on {args.executor}", unit="run", disable=not args.progress,
               dynamic_ncols=True)
    print(f"[cluster] {len(pending)} run(s) to train or evaluate as {args.executor} jobs; logs in "
          f"{logs_dir(args)}", flush=True)

    def say(text: str) -> None:
        tqdm.write(f"[cluster] {time.strftime('%Y-%m-%d %H:%M:%S')} {text}")

    while pending or active:
        room = max(window - len(active), 0)
        batch, pending = pending[:room], pending[room:]
        if batch:
            fns = [RunJob(args, a.k, len(runs), a.run_dir, a.ended) for a in batch]
            said = io.StringIO()  # submitit echoes sbatch's stderr on a refusal: it is in the one-line error
            try:
                with contextlib.redirect_stderr(said):
                    jobs = executor.submit_array(fns)
            except (FailedJobError, FailedSubmissionError) as e:
                bar.close()
                raise submission_error(args, e) from None
            sys.stderr.write(said.getvalue())
            for job, a in zip(jobs, batch):
                active[job] = a
                attempts[a.run_dir] += 1
        time.sleep(POLL_S[args.executor])
        for job in [j for j in active if j.done()]:
            a = active.pop(job)
            run = os.path.relpath(a.run_dir, args.runs)
            error = job.exception()
            if error is None:
                damaged += job.result()
                bar.update(1)
                if not args.progress:
                    say(f"{run}: done (job {job.job_id})")
                continue
            reason = failure_line(job, error)
            if attempts[a.run_dir] <= args.cluster_retries:
                say(f"{run}: job {job.job_id} {reason}; submitted again (attempt {attempts[a.run_dir] + 1} of "
                    f"{args.cluster_retries + 1}), its log: {job.paths.stderr}")
                pending.append(_Attempt(a.k, a.run_dir, (*a.ended, str(job.job_id))))
            else:
                say(f"{run}: job {job.job_id} {reason}; its log: {job.paths.stderr}")
                failed.append((run, reason, str(job.paths.stderr)))
                bar.update(1)
        if args.progress:
            bar.set_postfix_str(f"{len(active)} submitted, {len(pending)} waiting")
    bar.close()
    report_damaged(damaged, {})
    if failed:
        run, reason, log = failed[-1]
        raise ValueError(f"executor: {len(failed)} of {len(attempts)} runs failed {args.cluster_retries + 1} times "
                         f"(the last: {run}: {reason}; its log {log}); the others are recorded: run the command "
                         f"again to retry them (--cluster-retries), or build the tables with --from-records")
    return damaged


__all__ = ["POLL_S", "RunJob", "TIMEOUT_REQUEUES", "check_settings", "make_executor", "release_stale_locks",
           "sbatch_options", "submission_error", "work_off"]
