"""Faults and bad input: one-line errors naming the path or field, a lock per run directory, interrupts that
checkpoint and resume exactly, checkpoint write failures that keep the last committed checkpoint."""

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time

import jax
import numpy as np
import pytest
from test_training import bimodal_buffer, tiny_cfg

from hipolicy_jax import checkpoint
from hipolicy_jax.config import TrainConfig
from hipolicy_jax.data.dataset import SequenceDataset
from hipolicy_jax.data.replay_buffer import ReplayBuffer
from hipolicy_jax.envs import make
from hipolicy_jax.envs.demos import check_buffer_fits_env
from hipolicy_jax.runs.lock import RunLock, RunLockedError
from hipolicy_jax.runs.store import load_run
from hipolicy_jax.runs.train import RunConfig, prepare_out_dir
from hipolicy_jax.trainer import CheckpointWriteError, fit

WORKER = os.path.join(os.path.dirname(__file__), "workers", "fit_worker.py")
TRAIN = TrainConfig(batch_size=16, num_steps=12, warmup_steps=2, log_every=1, ckpt_every=4)


@pytest.fixture(scope="module")
def dataset():
    return SequenceDataset(bimodal_buffer(), tiny_cfg().chunk, obs_keys=("state",))


def _losses(out) -> dict[int, float]:
    rows = [json.loads(x) for x in open(os.path.join(out, "metrics.jsonl"))]
    return {r["step"]: r["loss"] for r in rows if r["kind"] == "train"}


def test_bad_paths_and_fields_name_themselves(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"checkpoint: .*/missing does not exist"):
        load_run(str(tmp_path / "missing"))
    (tmp_path / "empty" / "checkpoints").mkdir(parents=True)
    with pytest.raises(FileNotFoundError, match="checkpoint: no complete checkpoint under .*empty/checkpoints"):
        load_run(str(tmp_path / "empty"))
    with pytest.raises(ValueError, match=r"task: must be one of \['press_button'"):
        RunConfig(task="no_such_task")
    (tmp_path / "a_file").write_text("x")
    with pytest.raises(ValueError, match=r"out: .*a_file is a file"):
        prepare_out_dir(str(tmp_path / "a_file"))
    with pytest.raises(ValueError, match=r"out: cannot create the run directory .*a_file/run"):
        prepare_out_dir(str(tmp_path / "a_file" / "run"))


def test_demos_of_another_task_are_refused_before_training():
    env = make("press_button")
    ep = {"state": np.zeros((30, env.state_dim), np.float32), "action": np.zeros((30, 7), np.float32)}
    with pytest.raises(ValueError, match=r"d.zarr: data/action has frames of shape \(7,\), the press_button task "
                                         r"expects \(4,\)"):
        check_buffer_fits_env(ReplayBuffer.from_episodes([ep]), env, "d.zarr")
    ep = {"state": np.zeros((30, 3), np.float32), "action": np.zeros((30, 4), np.float32)}
    with pytest.raises(ValueError, match=r"data/state has frames of shape \(3,\)"):
        check_buffer_fits_env(ReplayBuffer.from_episodes([ep]), env, "d.zarr")


def test_corrupt_checkpoint_is_one_line(dataset, tmp_path):
    fit(tiny_cfg(), TrainConfig(batch_size=16, num_steps=2, warmup_steps=1, ckpt_every=2), dataset, str(tmp_path),
        progress=False, tensorboard=False)
    for root, _, files in os.walk(tmp_path / "checkpoints" / "2" / "state"):
        for f in files:
            if f not in ("_METADATA", "_CHECKPOINT_METADATA", "manifest.ocdbt"):
                with open(os.path.join(root, f), "r+b") as fh:
                    fh.truncate(os.path.getsize(os.path.join(root, f)) // 3)
    with pytest.raises(ValueError, match=r"checkpoint: .*checkpoints/2 is unreadable \(.*\); pass another --step"):
        checkpoint.load_policy(str(tmp_path / "checkpoints"))
    with pytest.raises(FileNotFoundError, match=r"no step 7 under .*\(steps: \[.*2\]\)"):
        checkpoint.load_policy(str(tmp_path / "checkpoints"), 7)


# ------------------------------------------------------------------------------------------- checked checkpoints
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"


def _stored_places(item_dir, target: bytes) -> list[tuple[str, int, int]]:
    """Where an array's bytes are stored under a checkpoint item's folder: ``(file, start, end)`` of each raw copy
    or of each zstd frame that decodes to bytes holding them (orbax's OCDBT data files are zstd frames)."""
    from numcodecs import Zstd

    places = []
    for root, _, files in os.walk(item_dir):
        for f in files:
            path = os.path.join(root, f)
            data = open(path, "rb").read()
            i = data.find(target)
            if i >= 0:
                places.append((path, i, i + len(target)))
                continue
            starts, m = [], data.find(ZSTD_MAGIC)
            while m >= 0:
                starts.append(m)
                m = data.find(ZSTD_MAGIC, m + 1)
            starts.append(len(data))
            for a in range(len(starts) - 1):
                for b in range(a + 1, len(starts)):  # a frame ends where a later magic starts
                    try:
                        decoded = Zstd().decode(data[starts[a]:starts[b]])
                    except Exception:  # noqa: BLE001 - the magic bytes occurred inside compressed data
                        continue
                    if target in decoded:
                        places.append((path, starts[a], starts[b]))
                    break
    return places


def _flip_bytes_of(item_dir, array) -> int:
    """Invert a byte three quarters into every stored copy of ``array``'s bytes under ``item_dir``, as a bad disk
    or an interrupted copy would; → how many places were damaged."""
    places = _stored_places(item_dir, np.ascontiguousarray(array).tobytes())
    for path, start, end in places:
        with open(path, "r+b") as fh:
            fh.seek(start + 3 * (end - start) // 4)
            byte = fh.read(1)
            fh.seek(-1, os.SEEK_CUR)
            fh.write(bytes([byte[0] ^ 0xFF]))
    return len(places)


@pytest.fixture(scope="module")
def two_checkpoints(dataset, tmp_path_factory):
    """A run stopped after step 3 of 4 with checkpoints at steps 2 and 3, and the same run trained to step 4. (At
    step 2 the EMA still equals the parameters: Diffusion Policy's decay is 0 for the first two updates.)"""
    root = tmp_path_factory.mktemp("checked")
    train = TrainConfig(batch_size=16, num_steps=4, warmup_steps=1, ckpt_every=1, ckpt_keep=2)
    stopped = fit(tiny_cfg(), train, dataset, str(root / "stopped"), progress=False, tensorboard=False, stop_at=3)
    full = fit(tiny_cfg(), train, dataset, str(root / "full"), progress=False, tensorboard=False)
    return root / "stopped", stopped, full, train


def _largest_leaf(tree):
    return max((np.asarray(x) for x in jax.tree.leaves(tree)), key=lambda x: x.size)


def test_checkpoints_store_the_checksum_of_every_tree_as_written(two_checkpoints, dataset):
    run, stopped, _, _ = two_checkpoints
    loaded = checkpoint.load_policy(str(run / "checkpoints"), 3)
    stored = loaded.meta["checksums"]
    assert tuple(stored) == checkpoint.CHECKED_TREES == ("step", "params", "ema_params", "opt_state", "normalizer")
    assert stored == checkpoint.checksums(stopped.state, dataset.normalizer.to_dict())  # the state at step 3
    assert stored["params"] != stored["ema_params"] and int(stopped.state.step) == loaded.step == 3
    np.testing.assert_array_equal(_largest_leaf(loaded.params), _largest_leaf(stopped.state.ema_params))


@pytest.mark.parametrize("tree", ["params", "ema_params", "opt_state", "normalizer"])
def test_a_damaged_tree_is_refused_in_one_line(two_checkpoints, dataset, tree, tmp_path):
    """A policy load (evaluate, calibrate, export, serve) reads and verifies the step, the EMA parameters and the
    normaliser; training's resume reads and verifies every tree, the raw parameters and optimiser state too."""
    run, stopped, _, train = two_checkpoints
    shutil.copytree(run, tmp_path / "run")
    ckpts = tmp_path / "run" / "checkpoints"
    if tree == "normalizer":
        damaged = _flip_bytes_of(ckpts / "3" / "normalizer", dataset.normalizer.to_dict()["action"]["scale"])
    else:
        damaged = _flip_bytes_of(ckpts / "3" / "state", _largest_leaf(getattr(stopped.state, tree)))
    assert damaged >= 1
    if tree in ("params", "opt_state"):  # not part of a trained policy: its load does not read them
        loaded = checkpoint.load_policy(str(ckpts))
        np.testing.assert_array_equal(_largest_leaf(loaded.params), _largest_leaf(stopped.state.ema_params))
        with pytest.raises(checkpoint.CheckpointDamaged, match=rf"step 3 at .* is damaged: its {tree} does not"):
            with checkpoint.Checkpointer(str(ckpts)) as ckpt:  # what resume reads
                ckpt.restore(3, jax.eval_shape(lambda: stopped.state))
        return
    with pytest.raises(ValueError) as info:
        checkpoint.load_policy(str(ckpts))
    msg = str(info.value)
    assert "\n" not in msg
    if tree == "normalizer":  # its small arrays sit beside OCDBT's own checked records: unreadable or damaged
        assert f"step 3 at {ckpts / '3'} is damaged: its normalizer does not match" in msg or \
            f"{ckpts / '3'} is unreadable" in msg, msg
    else:  # a flipped byte inside a zstd frame decodes to other numbers: only the checksum sees it
        assert isinstance(info.value, checkpoint.CheckpointDamaged) and info.value.trees == (tree,)
        assert msg == (f"checkpoint: step 3 at {ckpts / '3'} is damaged: its {tree} does not match the SHA-256 "
                       f"stored when it was written; pass another --step (steps: [2, 3]) or re-train")
    checkpoint.load_policy(str(ckpts), 2)  # the older step is intact and loads


def test_resume_falls_back_to_the_newest_checkpoint_that_verifies(two_checkpoints, dataset, tmp_path, capsys):
    run, stopped, full, train = two_checkpoints
    shutil.copytree(run, tmp_path / "run")
    ckpts = tmp_path / "run" / "checkpoints"
    assert _flip_bytes_of(ckpts / "3" / "state", _largest_leaf(stopped.state.params)) >= 1
    (ckpts / "corrupt_3").mkdir()  # set aside by an earlier resume: kept, never overwritten
    capsys.readouterr()
    res = fit(tiny_cfg(), train, dataset, str(tmp_path / "run"), progress=False, tensorboard=False)
    printed = capsys.readouterr().out.splitlines()
    said = [x for x in printed if "step 3 is damaged" in x]
    assert said == [f"[checkpoint] step 3 is damaged (its params does not match the SHA-256 stored when it was "
                    f"written); kept aside as {ckpts / 'corrupt_3.1'}, trying step 2"]
    assert "[checkpoint] resuming from step 2" in printed
    assert (ckpts / "corrupt_3").is_dir() and (ckpts / "corrupt_3.1" / "state").is_dir()
    assert res.start_step == 2
    np.testing.assert_allclose(res.losses, full.losses[2:], rtol=1e-6)  # the same run as if nothing was damaged


def test_a_checkpoint_without_checksums_loads_with_a_one_line_note(two_checkpoints, tmp_path, capsys):
    run, stopped, _, _ = two_checkpoints
    shutil.copytree(run / "checkpoints", tmp_path / "checkpoints")
    meta_file = tmp_path / "checkpoints" / "3" / "meta" / "metadata"
    meta = json.loads(meta_file.read_text())
    del meta["checksums"]  # as written before checksums were stored
    meta_file.write_text(json.dumps(meta))
    capsys.readouterr()
    loaded = checkpoint.load_policy(str(tmp_path / "checkpoints"))
    err = capsys.readouterr().err
    assert err == (f"[checkpoint] step 3 at {tmp_path / 'checkpoints' / '3'} carries no checksum (written before "
                   f"checksums were stored): loaded unchecked\n")
    np.testing.assert_array_equal(_largest_leaf(loaded.params), _largest_leaf(stopped.state.ema_params))


def test_one_owner_per_run_directory(tmp_path):
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (tmp_path / ".lock").write_text(json.dumps({"pid": sleeper.pid, "host": os.uname().nodename,
                                                    "started": "2026-12-01T00:00:00"}))
        with pytest.raises(RunLockedError, match=rf"in use by another training \(pid {sleeper.pid} on "):
            RunLock(str(tmp_path)).acquire()
    finally:
        sleeper.kill()
        sleeper.wait()
    with RunLock(str(tmp_path)) as lock:  # the owner is gone (as after kill -9): taken over
        assert json.loads((tmp_path / ".lock").read_text())["pid"] == os.getpid() == lock.owner["pid"]
        other = RunLock(str(tmp_path))
        other.owner = {"pid": os.getpid(), "host": "elsewhere"}
        with pytest.raises(RunLockedError, match=r"in use by a training on host"):
            other.acquire()
    assert not (tmp_path / ".lock").exists()  # released


@pytest.mark.slow
def test_sigterm_checkpoints_the_current_step_and_resume_is_exact(tmp_path):
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    full = subprocess.run([sys.executable, WORKER, str(tmp_path / "full"), "--steps", "16"], env=env,
                          capture_output=True, text=True, timeout=600)
    assert full.returncode == 0, full.stderr[-2000:]
    out = tmp_path / "stopped"
    proc = subprocess.Popen([sys.executable, WORKER, str(out), "--steps", "16", "--sleep", "0.4"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 300
    while time.time() < deadline:  # wait until step 6 is logged, between two periodic checkpoints (4, 8)
        if (out / "metrics.jsonl").exists() and len((out / "metrics.jsonl").read_text().splitlines()) >= 6:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err[-2000:]
    line = [x for x in err.splitlines() if x.startswith("interrupted by")]
    assert len(line) == 1 and "SIGTERM: stopped after step" in line[0] and "rerun the same command" in line[0]
    stopped_at = int(line[0].split("after step ")[1].split(",")[0])
    assert 6 <= stopped_at < 16 and (out / "checkpoints" / str(stopped_at)).is_dir()
    again = subprocess.run([sys.executable, WORKER, str(out), "--steps", "16"], env=env, capture_output=True,
                           text=True, timeout=600)
    assert again.returncode == 0, again.stderr[-2000:]
    assert json.loads(again.stdout.strip().splitlines()[-1])["start"] == stopped_at
    got, want = _losses(out), _losses(tmp_path / "full")
    assert sorted(got) == list(range(1, 17))
    np.testing.assert_allclose([got[s] for s in range(1, 17)], [want[s] for s in range(1, 17)], rtol=1e-6)


@pytest.mark.slow
def test_checkpoint_write_failure_is_one_line_and_keeps_the_last_checkpoint(dataset, tmp_path, monkeypatch):
    full = fit(tiny_cfg(), TRAIN, dataset, str(tmp_path / "full"), progress=False, tensorboard=False)
    save = checkpoint.Checkpointer.save

    def failing(self, step, *args, **kwargs):
        if step == 8:
            raise OSError(errno.ENOSPC, "No space left on device")
        return save(self, step, *args, **kwargs)

    monkeypatch.setattr(checkpoint.Checkpointer, "save", failing)
    with pytest.raises(CheckpointWriteError) as info:
        fit(tiny_cfg(), TRAIN, dataset, str(tmp_path / "run"), progress=False, tensorboard=False)
    msg = str(info.value)
    assert "\n" not in msg and "No space left on device" in msg and "MiB free" in msg
    assert f"{tmp_path / 'run' / 'checkpoints'}" in msg and "last committed checkpoint (step 4) is intact" in msg
    monkeypatch.setattr(checkpoint.Checkpointer, "save", save)
    res = fit(tiny_cfg(), TRAIN, dataset, str(tmp_path / "run"), progress=False, tensorboard=False)
    assert res.start_step == 4
    np.testing.assert_allclose(res.losses, full.losses[4:], rtol=1e-6)


def test_concurrent_demo_collection_happens_once_and_is_never_read_half_written(tmp_path, monkeypatch):
    """Two threads asking for one missing demo buffer: one collects, the other waits and loads it; a collection cut
    off leaves only its temporary (removed by the next), never a dataset at the path. (Processes, as a campaign's
    shards are: ``test_concurrent_demo_collection_across_processes_happens_once``.)"""
    import threading

    from hipolicy_jax.config import EncoderConfig
    from hipolicy_jax.envs import demos

    calls = []

    def slow_collect(task, num_episodes, key, obs_keys, **kwargs):
        calls.append(task)
        time.sleep(0.5)
        if task == "fails":
            raise KeyboardInterrupt  # cut off mid-collection
        return [{"state": np.full((5, 3), i, np.float32), "action": np.full((5, 4), i, np.float32)}
                for i in range(num_episodes)]

    monkeypatch.setattr(demos, "collect_demos", slow_collect)
    path = str(tmp_path / "data" / "demo.zarr")
    os.makedirs(path + ".partial-999")  # a collection killed earlier
    got = [None, None]

    def worker(i):
        got[i] = demos.load_or_collect("press_button", EncoderConfig(), 3, path, progress=False)

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert calls == ["press_button"]  # collected once
    for buffer in got:
        assert buffer.num_episodes == 3 and np.array_equal(buffer.data["state"], got[0].data["state"])
    assert sorted(os.listdir(tmp_path / "data")) == [".demo.zarr.lock", "demo.zarr"]  # the stale temporary is gone

    broken = str(tmp_path / "data" / "broken.zarr")
    with pytest.raises(KeyboardInterrupt):
        demos.load_or_collect("fails", EncoderConfig(), 3, broken, progress=False)
    assert not os.path.exists(broken)


COLLECT_RACER = """
import json, os, sys, time
import numpy as np
from hipolicy_jax.config import EncoderConfig
from hipolicy_jax.envs import demos

path, calls, me, other = sys.argv[1:5]

def slow_collect(task, num_episodes, key, obs_keys, **kwargs):  # smoke-size stand-in: this process's pid as data
    with open(calls, "a") as f:
        f.write(f"{os.getpid()}\\n")
    time.sleep(1.0)  # the other process reaches the lock while this one collects
    return [{"state": np.full((5, 3), os.getpid() + i, np.float32), "action": np.full((5, 4), i, np.float32)}
            for i in range(num_episodes)]

demos.collect_demos = slow_collect
open(me, "w").close()
while not os.path.exists(other):  # barrier: both processes ask for the buffer at the same moment
    time.sleep(0.01)
buffer = demos.load_or_collect("press_button", EncoderConfig(), 3, path, progress=False)
print(json.dumps({"pid": os.getpid(), "episodes": buffer.num_episodes,
                  "state": np.asarray(buffer.data["state"]).tolist()}))
"""


def test_concurrent_demo_collection_across_processes_happens_once(tmp_path):
    """Two PROCESSES (as a campaign's shards) racing for one missing demo buffer: exactly one collects (the other
    reports that it waits for the lock), both end with the collector's data, and only the dataset and its lock file
    are left. The collection is a stand-in that writes the collecting process's pid into the data, so a buffer
    collected twice cannot pass as one."""
    path, calls = str(tmp_path / "data" / "demo.zarr"), str(tmp_path / "calls")
    ready = [str(tmp_path / f"ready{i}") for i in range(2)]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    procs = [subprocess.Popen([sys.executable, "-c", COLLECT_RACER, path, calls, ready[i], ready[1 - i]], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), [err[-2000:] for _, err in outs]
    collectors = [int(x) for x in open(calls).read().split()]
    assert len(collectors) == 1 and collectors[0] in [p.pid for p in procs]  # collected once
    waited = [p.pid for p, (out, _) in zip(procs, outs) if "waiting for another process collecting" in out]
    assert len(waited) == 1 and waited[0] != collectors[0]  # the other process really met the held lock
    got = [json.loads(out.strip().splitlines()[-1]) for out, _ in outs]
    want = [np.full((5, 3), collectors[0] + i).tolist() for i in range(3)]
    for g in got:
        assert g["episodes"] == 3 and np.array_equal(g["state"], np.concatenate(want))
    assert sorted(os.listdir(tmp_path / "data")) == [".demo.zarr.lock", "demo.zarr"]



EXTERNAL_COLLECT_RACER = """
import os, sys, time
from hipolicy_jax.campaigns.campaign import Campaign, Column
from hipolicy_jax.runs import external

data, calls, me, other = sys.argv[1:5]

def slow_collect(name, episodes, path, *, num_points, max_steps, log=print):  # stand-in for the bridge's venv
    with open(calls, "a") as f:
        f.write(f"{os.getpid()} {name} {episodes} {num_points} {max_steps}\\n")
    time.sleep(1.0)  # the other process reaches the lock while this one collects
    if os.path.exists(path):
        raise FileExistsError(f"{path} already exists")  # what the bridge does when collecting twice
    os.makedirs(path)
    return "collected"

external.collect_demos = slow_collect
camp = Campaign("smoke", runs=os.path.join(data, "..", "runs"), data=data, progress=False)
cfg = camp.run_config("metaworld:assembly", Column("DP"), 0)
open(me, "w").close()
while not os.path.exists(other):  # barrier: both processes ask for the buffer at the same moment
    time.sleep(0.01)
print(camp.ensure_demos(cfg, 0))
"""


def test_concurrent_external_demo_collection_happens_once(tmp_path):
    """Two campaign PROCESSES (a ``metaworld main`` per core) needing one missing external demo buffer: exactly
    one runs the bridge's collection (the stand-in fails as the bridge does if asked to write an existing buffer),
    the other reports that it waits for the lock, and both return the same path."""
    data, calls = str(tmp_path / "data"), str(tmp_path / "calls")
    ready = [str(tmp_path / f"ready{i}") for i in range(2)]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    procs = [subprocess.Popen([sys.executable, "-c", EXTERNAL_COLLECT_RACER, data, calls, ready[i], ready[1 - i]],
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), [err[-2000:] for _, err in outs]
    lines = open(calls).read().splitlines()
    assert len(lines) == 1  # collected once
    pid, name, episodes, points, max_steps = lines[0].split()
    assert int(pid) in [p.pid for p in procs] and name == "metaworld:assembly" and int(max_steps) == 200
    waited = [p.pid for p, (out, _) in zip(procs, outs) if "waiting for another process collecting" in out]
    assert len(waited) == 1 and waited[0] != int(pid)  # the other process really met the held lock
    paths = {out.strip().splitlines()[-1] for out, _ in outs}
    assert len(paths) == 1 and os.path.isdir(paths.pop())


def test_no_startup_noise():
    """Importing the package (MuJoCo MJX included) prints nothing: no 'Failed to import warp' lines."""
    proc = subprocess.run([sys.executable, "-c", "import hipolicy_jax.envs, hipolicy_jax.evaluation"],
                          capture_output=True, text=True, timeout=300, env=dict(os.environ, JAX_PLATFORMS="cpu"))
    assert proc.returncode == 0 and proc.stdout == "" and "warp" not in proc.stderr, (proc.stdout, proc.stderr)


# ------------------------------------------------------------------------ failed writes, as a user sees them (CLI)
def _mount(*args) -> None:
    subprocess.run(["mount", *args], check=True, capture_output=True, text=True)


@pytest.fixture(scope="module")
def cli_demos(tmp_path_factory):
    """A path for 10 press_button demos: the first CLI run below collects them, the others reuse them."""
    return str(tmp_path_factory.mktemp("cli_demos") / "press_button_10.zarr")


def _train_cli(out, data, *flags, env=None) -> subprocess.Popen:
    """``python -m experiments.train`` on the default task with a tiny network, as a user runs it."""
    cmd = [sys.executable, "-m", "experiments.train", "--episodes", "10", "--data", data, "--out", str(out),
           "--policy.model.size", "tiny", "--no-final-eval", "--no-progress", "--eval.every", "0", *flags]
    return subprocess.Popen(cmd, cwd=os.path.dirname(os.path.dirname(__file__)), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, JAX_PLATFORMS="cpu", **(env or {})))


def _wait_for(path, proc, timeout=600.0) -> None:
    deadline = time.time() + timeout
    while not os.path.isdir(path):
        assert proc.poll() is None, proc.communicate()[1][-3000:]
        assert time.time() < deadline, f"{path} never appeared"
        time.sleep(0.02)


def _one_line_error(proc, timeout=600) -> str:
    """The process's stderr, asserted to be exactly one 'error: ...' line, with exit status 1."""
    _, err = proc.communicate(timeout=timeout)
    assert proc.returncode == 1, err[-3000:]
    assert err.count("\n") == 1 and err.startswith("error: "), err[-3000:]
    return err.strip()


def _can_mount() -> bool:
    """Whether this process may mount (root with the capability to): a 1 MiB tmpfs mounted and unmounted."""
    if os.geteuid() != 0:
        return False
    import tempfile

    with tempfile.TemporaryDirectory() as probe:
        mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", probe], capture_output=True)
        if mounted.returncode == 0:
            subprocess.run(["umount", probe], capture_output=True)
        return mounted.returncode == 0


@pytest.fixture(scope="module")
def mountable():
    """Skips where this process may not mount (CI runs as root and may)."""
    if not _can_mount():
        pytest.skip("mounts a tmpfs / a read-only bind mount: needs root allowed to mount")


@pytest.mark.slow
def test_disk_full_during_training_is_one_line_on_stderr(tmp_path, cli_demos, mountable):
    disk = tmp_path / "disk"
    disk.mkdir()
    _mount("-t", "tmpfs", "-o", "size=3m", "tmpfs", str(disk))
    try:  # the tiny network's optimiser state alone is larger than 3 MiB: the first checkpoint cannot be written
        err = _one_line_error(_train_cli(disk / "run", cli_demos, "--train.num-steps", "20"))
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)
    assert f"error: [Errno 28] writing a checkpoint to {disk / 'run' / 'checkpoints'} failed (No space left on " \
           f"device; " in err and "no checkpoint was committed yet: free space and rerun the same command" in err


@pytest.mark.slow
def test_checkpoints_turning_read_only_during_training_is_one_line_on_stderr(tmp_path, cli_demos, mountable):
    out = tmp_path / "run"
    proc = _train_cli(out, cli_demos, "--train.num-steps", "600", "--train.ckpt-every", "300")
    ckpts = out / "checkpoints"
    _wait_for(ckpts / "1", proc)  # the first checkpoint committed; the next is due at step 300
    _mount("--bind", str(ckpts), str(ckpts))
    try:
        _mount("-o", "remount,bind,ro", str(ckpts))
        err = _one_line_error(proc)
    finally:
        subprocess.run(["umount", "-l", str(ckpts)], check=False)
    assert f"error: [Errno 30] writing a checkpoint to {ckpts} failed (Read-only file system; " in err
    assert "the last committed checkpoint (step 1) is intact: make it writable and rerun the same command" in err
    assert sorted(os.listdir(ckpts)) == ["1"]


@pytest.mark.slow
def test_run_directory_removed_during_training_is_one_line_on_stderr(tmp_path, cli_demos):
    out = tmp_path / "run"
    proc = _train_cli(out, cli_demos, "--train.num-steps", "600", "--train.ckpt-every", "300")
    _wait_for(out / "checkpoints" / "1", proc)
    shutil.rmtree(out)
    err = _one_line_error(proc)
    assert err == (f"error: [Errno 2] writing a checkpoint to {out / 'checkpoints'} failed (No such file or "
                   f"directory): the directory was removed during training; rerun the same command to start again")
    assert not out.exists()  # nothing made it again behind the user's back
