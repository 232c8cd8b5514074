"""The training loop: batches → jitted train step → metrics, checkpoints and periodic evaluation.

Resume is exact: step k's batch is ``dataset.batch_indices(data_key, k)`` and its noise ``fold_in(noise_key, k)``,
both functions of the seed and the step only, and the restored ``TrainState`` carries the step. Re-running the same
command after a stop continues the same loss sequence.

Crash safety: orbax writes a step into a temporary directory and renames it when complete, so a run killed mid-write
leaves no half step behind (the leftover temporary directory is reported and removed). A step that is listed but
cannot be restored (truncated files) or whose trees differ from the checksums stored when it was written (damaged
files) is reported in one line, kept aside as ``checkpoints/corrupt_<step>`` (never deleted) and the next older
step is used.

Data parallelism: with several devices (or ``num_devices``) the batch is sharded over a ``("data",)`` mesh and the
state replicated (``parallel``); the loss sequence matches single-device training on the same global batches.

Outputs under ``out_dir``: ``checkpoints/<step>/``, ``metrics.jsonl`` (one JSON object per log / eval event) and
TensorBoard event files under ``tb/``.
"""

from __future__ import annotations

import asyncio
import errno
import gc
import inspect
import json
import logging
import os
import re
import shutil
import signal
import threading
import time
from typing import Callable, NamedTuple

import jax
import numpy as np
from tqdm.auto import tqdm

from hipolicy_jax import jsonio
from hipolicy_jax.checkpoint import (CheckpointDamaged, Checkpointer, config_from_dict, config_to_dict,
                                     quiet_failed_reads)
from hipolicy_jax.config import PolicyConfig, TrainConfig
from hipolicy_jax.models.policy_net import PolicyNet, init_policy_params, param_count
from hipolicy_jax import parallel
from hipolicy_jax.training import TrainState, init_train_state, make_optimizer, make_train_step


class TrainingInterrupted(Exception):
    """SIGINT / SIGTERM stopped training after a complete step whose checkpoint was written: rerunning resumes."""

    def __init__(self, signum: int, step: int, ckpt_dir: str):
        self.signum, self.step, self.ckpt_dir = signum, step, ckpt_dir
        name = signal.Signals(signum).name
        super().__init__(f"{name}: stopped after step {step}, checkpoint written to {ckpt_dir}; rerun the same "
                         f"command to resume")


class CheckpointWriteError(OSError):
    """A checkpoint could not be written (disk full, permissions, ...); the last committed one is intact."""


def _os_errno(error: BaseException) -> int | None:
    """The OS error number behind ``error``: an ``OSError`` in its chain, or the ``os_error_code`` tensorstore
    (orbax's writer) puts into its messages (e.g. RESOURCE_EXHAUSTED ... [os_error_code='28'] for a full disk)."""
    seen = error
    while seen is not None:
        if isinstance(seen, OSError) and seen.errno:
            return seen.errno
        match = re.search(r"os_error_code='?(\d+)", str(seen))
        if match:
            return int(match.group(1))
        seen = seen.__cause__ or seen.__context__
    return None


def _write_error(ckpt_dir: str, error: BaseException, last_step: int | None) -> BaseException:
    """A one-line ``CheckpointWriteError`` for an OS-level failure behind ``error``, else ``error`` itself."""
    code = _os_errno(error)
    if code is None:
        return error
    try:
        free = f"{shutil.disk_usage(ckpt_dir).free / 2**20:.0f} MiB free"
    except OSError:
        free = "free space unknown"
    if code == errno.ENOENT or not os.path.isdir(ckpt_dir):
        return CheckpointWriteError(code, f"writing a checkpoint to {ckpt_dir} failed ({os.strerror(code)}): the "
                                          f"directory was removed during training; rerun the same command to "
                                          f"start again")
    kept = f"the last committed checkpoint (step {last_step}) is intact" if last_step is not None else \
        "no checkpoint was committed yet"
    fix = {errno.ENOSPC: "free space", errno.EDQUOT: "free space", errno.EROFS: "make it writable",
           errno.EACCES: "make it writable", errno.EPERM: "make it writable"}.get(code, "fix that")
    return CheckpointWriteError(code, f"writing a checkpoint to {ckpt_dir} failed ({os.strerror(code)}; {free}); "
                                      f"{kept}: {fix} and rerun the same command to resume")


def _latest_step(ckpt: Checkpointer) -> int | None:
    """The newest committed step, or None when there is none or the directory cannot be read."""
    try:
        return ckpt.latest_step()
    except Exception:  # noqa: BLE001 - a removed or unreadable directory: nothing to name
        return None


class _QuietCheckpointThreads(logging.Filter):
    """Drops what orbax's background writers log when a write fails: absl's tracebacks from its threads and
    asyncio's "Task exception was never retrieved" for its serialisation tasks, logged when they are collected.
    ``fit`` raises the failure itself as one line (``CheckpointWriteError``) and counts the dropped records."""

    def __init__(self):
        super().__init__()
        self.dropped = 0
        self.failed = False  # a write failed: orbax's threads may still report it after fit has raised

    def filter(self, record: logging.LogRecord) -> bool:
        text = record.getMessage() if record.name == "asyncio" else ""
        ours = (record.levelno >= logging.ERROR and record.exc_info and "orbax" in record.pathname) or \
            ("orbax" in text and ("never retrieved" in text or "exception" in text))
        self.dropped += bool(ours)
        return not ours

    def __enter__(self):
        for name in ("absl", "asyncio"):
            logging.getLogger(name).addFilter(self)
        return self

    def __exit__(self, *exc):
        """After a failed write the filter stays on for the rest of the process: orbax's writer threads report
        the same failure when their signals time out, after ``fit`` has raised it as one line."""
        if self.failed:
            release_waiting_writers()
            self.dropped += retrieve_failed_writes()
            return
        for name in ("absl", "asyncio"):
            logging.getLogger(name).removeFilter(self)


def release_waiting_writers() -> int:
    """After a failed write, orbax's writer threads for the later stages of that save (metadata, commit) wait for
    a signal the failed stage never sends, for orbax's coordination timeout (300 s), and Python waits for them
    before it exits. Cancel them and send the signals they wait for, so that they end at once without writing;
    → how many were released. (orbax-checkpoint 0.12.8's ``_SignalingThread``: pinned in pyproject.toml.)"""
    from orbax.checkpoint._src.futures import future as ocp_future

    released = 0
    for thread in threading.enumerate():
        if isinstance(thread, ocp_future._SignalingThread) and thread.is_alive():
            thread.cancel()
            ocp_future.set_signals(thread._receive_signals, operation_id=thread._operation_id)
            released += 1
    return released


def retrieve_failed_writes() -> int:
    """Silence what a failed orbax write leaves behind, to be logged when it is collected (possibly at the
    interpreter's exit, after the one-line error): mark the exceptions of its finished, failed tasks as retrieved
    (``Future.exception()``) and close its coroutines that were created but never started (they would warn "never
    awaited"). Call once orbax's writers have stopped; → how many were silenced."""
    gc.collect()
    count = 0
    for obj in gc.get_objects():
        if isinstance(obj, asyncio.Future) and obj.done() and not obj.cancelled():
            error = obj.exception()  # retrieving it is the point
            if error is not None and "orbax" in repr(obj) + str(error):
                count += 1
        elif inspect.iscoroutine(obj) and "orbax" in obj.cr_code.co_filename and \
                inspect.getcoroutinestate(obj) == inspect.CORO_CREATED:
            obj.close()
            count += 1
    return count


class FitResult(NamedTuple):
    state: TrainState
    net: PolicyNet
    losses: list[float]  # per step, for the steps this call ran
    start_step: int  # the step this call resumed from (0 for a fresh run)
    meta: dict


def run_keys(seed: int) -> dict[str, jax.Array]:
    """Independent key streams for parameter init, data order and diffusion noise."""
    base = jax.random.key(seed)
    return {name: jax.random.fold_in(base, i) for i, name in enumerate(("init", "data", "noise", "eval"))}


def checkpoint_meta(cfg: PolicyConfig, train_cfg: TrainConfig, example_batch: dict, extra: dict | None = None) -> dict:
    """JSON facts needed to rebuild the network: configs, action dim, per-frame obs shapes."""
    shapes = {k: list(v.shape[3:]) for k, v in example_batch["obs"].items()}
    meta = {"policy": config_to_dict(cfg), "train": config_to_dict(train_cfg),
            "action_dim": int(example_batch["action"].shape[-1]), "obs_shapes": shapes}
    meta.update(extra or {})
    return meta


def _same_config(a: dict, b: dict) -> bool:
    """Whether two checkpoint metas describe the same trained policy: equal ``PolicyConfig`` (parsed, so fields
    a newer version dropped or added with their defaults do not matter), action dim and observation shapes.
    Inference settings are not part of a checkpoint, so they never block a resume."""
    same_shapes = all(json.dumps(a.get(k), sort_keys=True) == json.dumps(b.get(k), sort_keys=True)
                      for k in ("action_dim", "obs_shapes"))
    return same_shapes and config_from_dict(PolicyConfig, a["policy"]) == config_from_dict(PolicyConfig, b["policy"])


def _report(msg: str) -> None:
    print(f"[checkpoint] {msg}", flush=True)


def clean_incomplete_writes(directory: str) -> list[str]:
    """Remove orbax's temporary directories left by a write that never committed; → their names."""
    if not os.path.isdir(directory):
        return []
    leftovers = sorted(d for d in os.listdir(directory) if "orbax-checkpoint-tmp" in d)
    for d in leftovers:
        shutil.rmtree(os.path.join(directory, d), ignore_errors=True)
        _report(f"removed incomplete checkpoint write {d} (the run stopped while saving)")
    return leftovers


def set_aside(directory: str, step: int) -> str:
    """Rename ``<directory>/<step>`` to the first free ``corrupt_<step>[.k]`` (a damaged checkpoint is kept for
    inspection, never deleted); → the new path."""
    aside, k = os.path.join(directory, f"corrupt_{step}"), 0
    while os.path.exists(aside):
        k += 1
        aside = os.path.join(directory, f"corrupt_{step}.{k}")
    os.rename(os.path.join(directory, str(step)), aside)
    return aside


def restore_newest_readable(directory: str, abstract, meta: dict):
    """Restore the newest checkpoint that reads back and matches its checksums; set the others aside
    (``set_aside``), one line each. → (state, step) or (None, None).

    Raises ValueError when the newest readable checkpoint belongs to a different config.
    """
    with Checkpointer(directory) as probe:
        steps = sorted(probe.all_steps(), reverse=True)
    for step in steps:
        try:
            with Checkpointer(directory) as ckpt:
                old = ckpt.restore_meta(step)
                if not _same_config(old, meta):
                    raise ValueError(f"{os.path.dirname(directory)} holds checkpoints of a different policy config "
                                     f"or data shapes; pass a new output directory or delete the old one")
                state, _, _ = ckpt.restore(step, abstract)
            return state, step
        except CheckpointDamaged as e:
            why = e.what()
        except Exception as e:  # noqa: BLE001 — any read failure means this step is unusable
            if isinstance(e, ValueError) and "different policy config" in str(e):
                raise
            quiet_failed_reads()
            why = f"unreadable: {type(e).__name__}: {str(e).splitlines()[0][:200] if str(e) else ''}"
        aside = set_aside(directory, step)
        older = [s for s in steps if s < step]
        _report(f"step {step} is damaged ({why}); kept aside as {aside}, "
                + (f"trying step {older[0]}" if older else "no older checkpoint: training starts from step 0"))
    return None, None


def _logged_train_rows(out_dir: str, upto: int) -> dict[int, dict]:
    """The train rows of ``metrics.jsonl`` up to step ``upto`` by step; a step logged twice (re-run after a
    resume) keeps its latest row."""
    path = os.path.join(out_dir, "metrics.jsonl")
    rows: dict[int, dict] = {}
    if os.path.exists(path):
        with open(path) as f:
            for line in f:
                row = json.loads(line)
                if row.get("kind") == "train" and row["step"] <= upto:
                    rows[row["step"]] = row
    return rows


def logged_train_cpu_seconds(out_dir: str, upto: int) -> float | None:
    """Process CPU seconds the logged training steps up to ``upto`` took (each train row's steps since the previous
    row × its ``cpu_s_per_step``; a step logged twice counts once): what earlier sessions of a resumed run used.
    None when a row predates the CPU measurement (no ``cpu_s_per_step``); 0 without rows."""
    seconds, prev = 0.0, 0
    rows = _logged_train_rows(out_dir, upto)
    for step in sorted(rows):
        if rows[step].get("cpu_s_per_step") is None:
            return None
        seconds += (step - prev) * rows[step]["cpu_s_per_step"]
        prev = step
    return seconds


def logged_train_seconds(out_dir: str, upto: int) -> float:
    """Seconds the logged training steps up to ``upto`` took, from ``metrics.jsonl`` (each train row's steps since
    the previous row / its ``steps_per_s``; a step logged twice — re-run after a resume — counts once, its latest
    row): what earlier sessions of a resumed run spent, so a run's wall time covers all its sessions."""
    rate = {step: row["steps_per_s"] for step, row in _logged_train_rows(out_dir, upto).items()
            if row.get("steps_per_s")}
    seconds, prev = 0.0, 0
    for step in sorted(rate):
        seconds += (step - prev) / rate[step]
        prev = step
    return seconds


class _Logger:
    """metrics.jsonl and TensorBoard; ``out_dir`` None logs nothing (the other processes of a multi-process run)."""

    def __init__(self, out_dir: str | None, tensorboard: bool):
        self._jsonl = open(os.path.join(out_dir, "metrics.jsonl"), "a") if out_dir else None
        self._tb = None
        if tensorboard:
            from tensorboardX import SummaryWriter

            self._tb = SummaryWriter(os.path.join(out_dir, "tb"))

    def log(self, step: int, kind: str, values: dict):
        if self._jsonl is None:
            return
        self._jsonl.write(jsonio.dumps({"step": step, "kind": kind, **values}) + "\n")
        self._jsonl.flush()
        if self._tb is not None:
            for k, v in values.items():
                if isinstance(v, (int, float)) and np.isfinite(v):
                    self._tb.add_scalar(f"{kind}/{k}", v, step)

    def close(self):
        if self._jsonl is not None:
            self._jsonl.close()
        if self._tb is not None:
            self._tb.close()


def fit(cfg: PolicyConfig, train_cfg: TrainConfig, dataset, out_dir: str, *,
        eval_fn: Callable[[TrainState, int], dict] | None = None, eval_every: int | None = None,
        meta_extra: dict | None = None, progress: bool = True, tensorboard: bool = True,
        stop_at: int | None = None, num_devices: int | None = None) -> FitResult:
    """Train (or resume) a policy on ``dataset`` (a ``data.dataset.SequenceDataset``).

    ``eval_fn(state, step) -> dict`` runs every ``eval_every`` steps and at the end; its scalars are logged.
    ``stop_at`` stops early after that step (used to simulate an interrupted run) without a final evaluation.
    ``num_devices``: data-parallel devices (default: all local devices).
    """
    os.makedirs(out_dir, exist_ok=True)
    keys = run_keys(train_cfg.seed)
    if len(dataset) < train_cfg.batch_size:
        raise ValueError(f"train.batch_size: {train_cfg.batch_size} exceeds the dataset's {len(dataset)} samples")
    example = dataset.get_batch(np.arange(min(2, len(dataset))))
    action_dim = int(example["action"].shape[-1])
    net = PolicyNet(cfg, action_dim)
    tx = make_optimizer(train_cfg)
    meta = checkpoint_meta(cfg, train_cfg, example, meta_extra)

    mesh = parallel.make_mesh(num_devices)
    parallel.check_batch_size(train_cfg.batch_size, mesh)
    ckpt_dir = os.path.join(out_dir, "checkpoints")
    if parallel.is_primary():
        clean_incomplete_writes(ckpt_dir)

    def fresh():
        return init_train_state(init_policy_params(cfg, action_dim, example["obs"], keys["init"]), tx)

    state, restored = None, None
    if os.path.isdir(ckpt_dir):
        state, restored = restore_newest_readable(ckpt_dir, jax.eval_shape(fresh), meta)
    if state is None:
        state = fresh()
    else:
        _report(f"resuming from step {restored}")
    state = parallel.replicate(parallel.to_host(state) if jax.process_count() > 1 else state, mesh)
    ckpt = Checkpointer(ckpt_dir, train_cfg.ckpt_every, train_cfg.ckpt_keep)
    start = int(parallel.to_host(state.step))
    meta["param_count"] = param_count(state.params)
    meta["num_devices"] = 1 if mesh is None else mesh.size
    train_step = make_train_step(net, cfg, train_cfg, tx)
    logger = _Logger(out_dir, tensorboard) if parallel.is_primary() else _Logger(None, False)
    end = train_cfg.num_steps if stop_at is None else min(stop_at, train_cfg.num_steps)
    losses: list[float] = []
    pending: list[dict] = []
    bar = tqdm(total=train_cfg.num_steps, initial=start, disable=not progress or not parallel.is_primary(),
               desc="train", unit="step",
               dynamic_ncols=True)
    t_last, n_last, c_last = time.perf_counter(), start, time.process_time()
    stop: dict = {"signum": None}

    def on_signal(signum, frame):
        if stop["signum"] is not None:  # a second signal: stop at once
            raise KeyboardInterrupt
        stop["signum"] = signum

    quiet = _QuietCheckpointThreads().__enter__()  # until the checkpointer is closed and its tasks collected
    handlers = {}
    if threading.current_thread() is threading.main_thread():
        handlers = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}

    def flush(done: int):
        nonlocal pending, t_last, n_last, c_last
        host = parallel.to_host(pending)
        pending = []
        bad = [m for m in host if not m["finite"]]
        if bad:
            raise FloatingPointError(
                f"non-finite loss or gradient at step ~{done} (loss={bad[0]['loss']}, grad_norm="
                f"{bad[0]['grad_norm']}); the update was skipped and the last checkpoint is intact. "
                f"Try a lower train.lr, train.grad_clip, or check the data for outliers")
        losses.extend(float(m["loss"]) for m in host)
        now, cpu = time.perf_counter(), time.process_time()
        sps = (done - n_last) / max(now - t_last, 1e-9)
        # process CPU seconds per step (all its threads): the cost, whatever else shared the cores
        cpu_per_step = (cpu - c_last) / max(done - n_last, 1)
        t_last, n_last, c_last = now, done, cpu
        row = {"loss": float(np.mean([m["loss"] for m in host])),
               "grad_norm": float(np.mean([m["grad_norm"] for m in host])), "lr": float(host[-1]["lr"]),
               "steps_per_s": sps, "cpu_s_per_step": cpu_per_step}
        logger.log(done, "train", row)
        bar.set_postfix(loss=f"{row['loss']:.4f}", lr=f"{row['lr']:.1e}", sps=f"{sps:.1f}")
        bar.update(done - bar.n)

    def save(done: int | None, force: bool = False, wait: bool = False):
        """Save step ``done`` (None: only wait for the writes in flight); OS-level failures become one line."""
        try:
            if done is not None:
                ckpt.save(done, state, dataset.normalizer, meta, force=force)
            if wait:
                ckpt.wait()
        except Exception as e:  # noqa: BLE001 - the rest propagate unchanged from _write_error
            quiet.failed = True
            raise _write_error(ckpt_dir, e, _latest_step(ckpt)) from e

    try:
        for step in range(start, end):
            batch = dataset.get_batch(dataset.batch_indices(keys["data"], step, train_cfg.batch_size))
            batch = parallel.shard_batch(batch, mesh)
            state, metrics = train_step(state, batch, keys["noise"])
            pending.append(metrics)
            done = step + 1
            if done % train_cfg.log_every == 0 or done == end or stop["signum"] is not None:
                flush(done)
            if stop["signum"] is not None:
                save(done, force=True, wait=True)
                raise TrainingInterrupted(stop["signum"], done, ckpt_dir)
            save(done, force=(done == train_cfg.num_steps))
            if eval_fn is not None and eval_every and done % eval_every == 0 and done < train_cfg.num_steps:
                logger.log(done, "eval", eval_fn(state, done))
        if eval_fn is not None and end == train_cfg.num_steps:
            logger.log(end, "eval", eval_fn(state, end))
        save(None, wait=True)
    finally:
        for sig, old in handlers.items():
            signal.signal(sig, old)
        bar.close()
        try:
            ckpt.wait()
        except Exception:  # noqa: BLE001 - already reported by save(); do not hide the exception in flight
            pass
        ckpt.close()
        logger.close()
        quiet.__exit__()
    return FitResult(state, net, losses, start, meta)
