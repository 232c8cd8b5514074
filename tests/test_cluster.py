"""Campaigns through submitit (``campaigns.cluster``): one job a run on the local executor gives the in-process
campaign's records, a job killed mid-training is submitted again and resumes from its checkpoint, and a machine that
cannot submit to SLURM, or a partition sbatch refuses, is a one-line error."""

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from experiments import paper
from hipolicy_jax.campaigns import cluster, tables
from hipolicy_jax.runs.lock import CAMPAIGN_LOCK_FILE, LOCK_FILE, RunLock

# the smallest campaign: the main table's two runs (DP and DP+HiPolicy) of one task and seed, 2 episodes each
SMALL = ["campaign", "--budget", "smoke", "--tasks", "press_button", "--seeds", "0", "--baseline-seeds", "--regimes",
         "r100", "--obs-types", "state", "--only", "main", "--episodes", "2", "--readme", "", "--no-progress"]
OUTCOMES = ("settings", "success", "steps", "decisions", "thresholds", "success_rate")


def argv(root: Path, data: Path, *extra: str) -> list[str]:
    return [*SMALL, "--runs", str(root / "runs"), "--records", str(root / "records"), "--results",
            str(root / "results"), "--data", str(data), *extra]


def evaluations(records: Path) -> dict[str, dict]:
    """Per record (its path under ``records``) and evaluation: the per-episode outcomes and what they ran with."""
    out = {}
    for path in sorted(records.rglob("*.json")):
        rec = json.loads(path.read_text())
        for key, ev in rec["evaluations"].items():
            out[f"{path.relative_to(records)} {key}"] = {f: ev[f] for f in OUTCOMES}
    return out


@pytest.fixture(scope="module")
def inprocess(tmp_path_factory):
    """The small campaign in-process, as ``python -m experiments.paper campaign`` runs it; the demos and the XLA
    compilation cache are shared with the executor's jobs (→ (root, data dir, cache dir))."""
    root = tmp_path_factory.mktemp("cluster")
    data, cache = root / "data", root / "xla"
    env = dict(os.environ, JAX_PLATFORMS="cpu", JAX_COMPILATION_CACHE_DIR=str(cache))
    done = subprocess.run([sys.executable, "-m", "experiments.paper", *argv(root / "inprocess", data)], env=env,
                          capture_output=True, text=True, timeout=1200)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert len(evaluations(root / "inprocess" / "records")) == 2
    return root, data, cache


@pytest.mark.slow  # a smoke campaign through submitit's local executor: in CI's slow guards
def test_local_executor_gives_the_in_process_records(inprocess, tmp_path, monkeypatch, capsys):
    """Two runs as two local submitit jobs: the same evaluations with the same per-episode outcomes as in-process,
    written by the jobs into the records; the submitter then builds the tables from them."""
    root, data, cache = inprocess
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(cache))
    args = paper.parse_args(argv(tmp_path, data, "--executor", "local", "--cluster-logs", str(tmp_path / "logs")))
    index = tables.campaign_table(args)
    out = capsys.readouterr().out
    assert evaluations(tmp_path / "records") == evaluations(root / "inprocess" / "records")
    done = [line for line in out.splitlines() if line.startswith("[cluster]") and ": done (job " in line]
    assert sorted(line.split()[3] for line in done) == ["smoke/press_button/state/dp/seed0:",
                                                        "smoke/press_button/state/hipolicy/seed0:"]
    assert len(list((tmp_path / "logs").glob("*_result.pkl"))) == 2  # one job a run
    assert Path(index).name == "campaign.md" and (tmp_path / "results" / "main.md").exists()
    assert "--executor local" in Path(index).read_text()
    # everything recorded: a second campaign submits nothing
    tables.campaign_table(args)
    assert "[cluster]" not in capsys.readouterr().out


@pytest.mark.slow  # a smoke campaign through submitit's local executor: in CI's slow guards
def test_a_killed_job_is_submitted_again_and_resumes_from_its_checkpoint(inprocess, tmp_path, monkeypatch, capsys):
    """The DP run's job (``--shard 0 2``: that run alone) killed with SIGKILL once its step-6 checkpoint is written:
    the submitter submits it again, the new job takes over the dead job's locks, resumes the training from its
    checkpoint and records the same evaluation as the uninterrupted in-process run."""
    root, data, cache = inprocess
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(cache))
    args = paper.parse_args(argv(tmp_path, data, "--executor", "local", "--shard", "0", "2", "--cluster-logs",
                                 str(tmp_path / "logs")))
    run = tmp_path / "runs" / "smoke" / "press_button" / "state" / "dp" / "seed0"
    killed, stop = [], threading.Event()

    def kill_mid_training():
        while not stop.is_set():
            if (run / "checkpoints" / "6").is_dir() and not (run / "summary.json").exists():
                try:
                    pid = json.loads((run / LOCK_FILE).read_text())["pid"]  # the training job's process
                except (OSError, ValueError, KeyError):
                    continue
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
                return
            time.sleep(0.02)

    killer = threading.Thread(target=kill_mid_training, daemon=True)
    killer.start()
    try:
        tables.campaign_table(args)
    finally:
        stop.set()
        killer.join()
    out = capsys.readouterr().out
    assert killed, "the job finished before its step-6 checkpoint was seen"
    again = [line for line in out.splitlines() if "submitted again (attempt 2 of 3)" in line]
    assert len(again) == 1 and "smoke/press_button/state/dp/seed0: job " in again[0]
    assert "ended without a result" in again[0]
    logs = "".join(p.read_text() for p in (tmp_path / "logs").glob("*_log.out"))
    assert f"taking over {run / CAMPAIGN_LOCK_FILE}: its owner (pid {killed[0]} on " in logs
    resumed = [int(line.split("resuming from step ")[1]) for line in logs.splitlines() if "resuming from step" in line]
    assert len(resumed) == 1 and resumed[0] >= 6
    want = {k: v for k, v in evaluations(root / "inprocess" / "records").items() if k.startswith(
        os.path.join("smoke", "press_button", "state", "dp"))}
    assert evaluations(tmp_path / "records") == want
    assert json.loads((run / "summary.json").read_text())["steps"] == 12


def test_slurm_without_sbatch_is_one_line(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))  # no sbatch here
    args = paper.parse_args(argv(tmp_path, tmp_path / "data", "--executor", "slurm"))
    with pytest.raises(ValueError) as info:
        tables.campaign_table(args)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith("executor: --executor slurm submits with sbatch, and there is no sbatch")
    assert "pass --executor local" in msg
    assert not (tmp_path / "runs" / "smoke").exists()  # nothing trained here instead
    env = dict(os.environ, PATH=str(tmp_path), JAX_PLATFORMS="cpu")  # the command line: that line, no traceback
    cli = subprocess.run([sys.executable, "-m", "experiments.paper", *argv(tmp_path, tmp_path / "data", "--executor",
                                                                         "slurm")],
                         env=env, capture_output=True, text=True, timeout=300)
    assert cli.returncode == 1 and cli.stderr.strip() == f"error: {msg}"


def test_a_partition_sbatch_refuses_is_one_line_naming_the_flag(tmp_path, monkeypatch, capsys):
    """sbatch (a stand-in on PATH that keeps the script it is given and refuses its partition as sbatch does): the
    job array's script carries the --slurm-* settings, and the refusal is one line naming --slurm-partition."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "sbatch").write_text(f'#!/bin/sh\ncp "$1" {tmp_path}/submitted.sh\n'
                                    'echo "sbatch: error: invalid partition specified: nosuch" >&2\n'
                                    'echo "sbatch: error: Batch job submission failed: Invalid partition name '
                                    'specified" >&2\nexit 1\n')
    (bin_dir / "srun").write_text("#!/bin/sh\nexit 0\n")
    for f in bin_dir.iterdir():
        f.chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    args = paper.parse_args(argv(tmp_path, tmp_path / "data", "--executor", "slurm", "--slurm-partition", "nosuch",
                                 "--cluster-time-min", "90", "--slurm-mem-gb", "8", "--slurm-account", "lab",
                                 "--slurm-sbatch", "qos=high", "--cluster-parallel", "1"))
    with pytest.raises(ValueError) as info:
        tables.campaign_table(args)
    msg = str(info.value)
    assert msg == ("slurm-partition: sbatch refused the job array on partition 'nosuch' (sbatch: error: Batch job "
                   "submission failed: Invalid partition name specified); pass --slurm-partition with one that "
                   "`sinfo -s` lists")
    assert "sbatch: error" not in capsys.readouterr().err  # said once, in that line
    script = (tmp_path / "submitted.sh").read_text()
    for line in ("--partition=nosuch", "--time=90", "--cpus-per-task=2", "--mem=8GB", "--account=lab", "--qos=high",
                 "--array=0-1%1", "--signal=USR2@90"):
        assert f"#SBATCH {line}\n" in script
    assert not (tmp_path / "runs" / "smoke").exists()


def test_cluster_settings_and_locks_of_ended_attempts(tmp_path, monkeypatch):
    """Settings out of range are one line naming their flag; under SLURM a lock names its job, and a later attempt
    releases the locks an ended attempt left (from any host), not others; a requeued job is the same job."""
    base = paper.parse_args(SMALL)
    for flags, start in ((["--cluster-time-min", "0"], "cluster-time-min: expected a number >= 1, got 0"),
                         (["--cluster-retries", "-1"], "cluster-retries: expected a number >= 0, got -1"),
                         (["--slurm-sbatch", "qos"], "slurm-sbatch: expected KEY=VALUE")):
        with pytest.raises(ValueError, match="^" + start) as info:
            cluster.check_settings(paper.parse_args(SMALL + flags))
        assert "\n" not in str(info.value)
    assert cluster.sbatch_options(("qos=high", "--gres=gpu:1")) == {"qos": "high", "gres": "gpu:1"}
    assert cluster.logs_dir(base) == os.path.join(base.runs, "cluster-logs")

    monkeypatch.setenv("SLURM_JOB_ID", "1236")
    monkeypatch.setenv("SLURM_ARRAY_JOB_ID", "1234")
    monkeypatch.setenv("SLURM_ARRAY_TASK_ID", "2")
    with RunLock(str(tmp_path), CAMPAIGN_LOCK_FILE):
        assert json.loads((tmp_path / CAMPAIGN_LOCK_FILE).read_text())["job"] == "1234_2"  # as sacct names it
    (tmp_path / CAMPAIGN_LOCK_FILE).write_text(json.dumps({"pid": 4242, "host": "node7", "job": "1234_2"}))
    (tmp_path / LOCK_FILE).write_text(json.dumps({"pid": 4243, "host": "node8", "job": "999_0"}))
    assert cluster.release_stale_locks(str(tmp_path), {"1234_2"}) == [str(tmp_path / CAMPAIGN_LOCK_FILE)]
    assert (tmp_path / LOCK_FILE).exists()  # another job's: left alone

    job = cluster.RunJob(base, 1, 2, "runs/x", ("7",))
    requeued = job.checkpoint()
    assert requeued.function is job and requeued.args == () and job.ended == ("7",)
