"""Data-parallel training on 4 forced CPU devices, kill -9 and resume, corrupted / partial checkpoints."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from test_training import bimodal_buffer, tiny_cfg

from hipolicy_jax.config import TrainConfig
from hipolicy_jax.data.dataset import SequenceDataset
from hipolicy_jax.trainer import fit

WORKER = os.path.join(os.path.dirname(__file__), "workers", "fit_worker.py")


def _env(devices: int | None = None) -> dict:
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    if devices:
        env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
    return env


def _run(out, *extra, devices=None) -> dict:
    proc = subprocess.run([sys.executable, WORKER, str(out), *extra], env=_env(devices), capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _step_losses(out) -> dict[int, float]:
    """Per-step losses from metrics.jsonl (log_every=1); a resumed run's rows overwrite the same steps."""
    rows = [json.loads(x) for x in open(os.path.join(out, "metrics.jsonl"))]
    return {r["step"]: r["loss"] for r in rows if r["kind"] == "train"}


@pytest.mark.slow
def test_four_devices_match_one_device(tmp_path):
    four = _run(tmp_path / "four", "--steps", "6", "--devices", "4", devices=4)
    one = _run(tmp_path / "one", "--steps", "6", "--devices", "1", devices=4)
    assert four["devices"] == 4 and one["devices"] == 1
    np.testing.assert_allclose(four["losses"], one["losses"], rtol=1e-4, atol=1e-6)


@pytest.mark.slow
def test_kill_9_then_rerun_resumes_and_matches_uninterrupted(tmp_path):
    full = _run(tmp_path / "full", "--steps", "16")
    out = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, WORKER, str(out), "--steps", "16", "--sleep", "0.3"], env=_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ckpts = out / "checkpoints"
    deadline = time.time() + 300
    while time.time() < deadline:  # wait until the step-8 checkpoint has committed, then kill hard
        if (ckpts / "8").is_dir() and any(f.name == "_CHECKPOINT_METADATA" for f in (ckpts / "8").iterdir()):
            break
        time.sleep(0.1)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    resumed = _run(out, "--steps", "16")
    assert resumed["start"] in (8, 12)
    got, want = _step_losses(out), _step_losses(tmp_path / "full")
    assert sorted(got) == list(range(1, 17))
    np.testing.assert_allclose([got[s] for s in range(1, 17)], [want[s] for s in range(1, 17)], rtol=1e-6)
    assert full["start"] == 0


@pytest.mark.slow
def test_partial_write_and_corrupted_checkpoint_are_reported_and_skipped(tmp_path, capsys):
    ds = SequenceDataset(bimodal_buffer(), tiny_cfg().chunk, obs_keys=("state",))
    train_cfg = TrainConfig(batch_size=16, num_steps=12, warmup_steps=2, log_every=1, ckpt_every=4)
    full = fit(tiny_cfg(), train_cfg, ds, str(tmp_path / "full"), progress=False, tensorboard=False)
    out = tmp_path / "run"
    fit(tiny_cfg(), train_cfg, ds, str(out), progress=False, tensorboard=False, stop_at=8)
    ckpts = out / "checkpoints"
    # a write that never committed (as after kill -9 mid-save) ...
    partial = ckpts / "12.orbax-checkpoint-tmp-1234567"
    (partial / "state").mkdir(parents=True)
    (partial / "state" / "junk").write_bytes(b"\0" * 10)
    # ... and a committed step whose array files were damaged afterwards
    for root, _, files in os.walk(ckpts / "8" / "state"):
        for f in files:
            if f not in ("_METADATA", "_CHECKPOINT_METADATA", "manifest.ocdbt"):
                with open(os.path.join(root, f), "r+b") as fh:
                    fh.truncate(max(0, os.path.getsize(os.path.join(root, f)) // 3))
    res = fit(tiny_cfg(), train_cfg, ds, str(out), progress=False, tensorboard=False)
    printed = capsys.readouterr().out
    assert "incomplete checkpoint write 12.orbax-checkpoint-tmp-1234567" in printed
    assert "step 8 is damaged (unreadable: " in printed and "trying step 4" in printed and (ckpts / "corrupt_8").is_dir()
    assert res.start_step == 4
    np.testing.assert_allclose(res.losses, full.losses[4:], rtol=1e-6)


@pytest.mark.slow
def test_evaluation_shards_episodes_across_devices():
    worker = os.path.join(os.path.dirname(__file__), "workers", "eval_worker.py")
    outs = []
    for devices in (4, None):
        proc = subprocess.run([sys.executable, worker], env=_env(devices), capture_output=True, text=True,
                              timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
        outs.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    four, one = outs
    assert four["devices"] == 4 and "NamedSharding" in four["sharding"] and "'data'" in four["sharding"]
    assert four["steps"] == one["steps"] and four["success"] == one["success"]


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _two_processes(out, *extra) -> list[dict]:
    """Run tests/workers/dist_worker.py as 2 processes of 2 CPU devices each on 127.0.0.1 (gloo)."""
    worker = os.path.join(os.path.dirname(__file__), "workers", "dist_worker.py")
    port = _free_port()
    procs = [subprocess.Popen([sys.executable, worker, str(out), *extra], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True,
                              env=dict(_env(), JAX_COORDINATOR_ADDRESS=f"127.0.0.1:{port}", JAX_NUM_PROCESSES="2",
                                       JAX_PROCESS_ID=str(i), JAX_NUM_CPU_DEVICES="2"))
             for i in range(2)]
    outs = []
    for p in procs:
        stdout, stderr = p.communicate(timeout=600)
        assert p.returncode == 0, stderr[-3000:]
        outs.append(json.loads(stdout.strip().splitlines()[-1]))
    return sorted(outs, key=lambda o: o["process"])


@pytest.mark.slow
def test_two_processes_match_one_process_and_resume(tmp_path):
    """2 processes × 2 CPU devices (gloo) train the same loss sequence as 1 process × 4 devices; each process holds
    its own half of every batch; the checkpoint written at step 10 is restored by both processes."""
    one = _run(tmp_path / "one", "--steps", "20", "--devices", "4", devices=4)
    first = _two_processes(tmp_path / "two", "--steps", "20", "--stop-at", "10")
    assert [(o["process"], o["processes"], o["devices"], o["start"]) for o in first] == [(0, 2, 4, 0), (1, 2, 4, 0)]
    halves = [set(o["local_rows"]) for o in first]
    assert not halves[0] & halves[1] and sorted(halves[0] | halves[1]) == sorted(first[0]["global_batch"])
    assert len(halves[0]) == len(halves[1]) == 8
    assert sorted(os.listdir(tmp_path / "two" / "checkpoints")) == ["1", "10", "5"]  # written once, not per process
    rest = _two_processes(tmp_path / "two", "--steps", "20")
    assert [o["start"] for o in rest] == [10, 10] and rest[0]["losses"] == rest[1]["losses"]
    losses = _step_losses(tmp_path / "two")  # process 0 logs
    np.testing.assert_allclose([losses[s] for s in range(1, 21)], one["losses"], rtol=1e-4)
