"""Orbax checkpoints: train state, normaliser and a JSON ``meta`` (configs, shapes, thresholds) per step.

Layout: ``<dir>/<step>/{state, normalizer, meta}``. ``meta`` carries everything needed to rebuild the network
without the training script: the policy config, the action dimension and the per-frame observation shapes.
A checkpoint is only listed by orbax once its write committed, so a run killed mid-write resumes from the
previous complete step.

Checked: ``meta["checksums"]`` holds the SHA-256 (``tree_sha256``) of every saved tree (``CHECKED_TREES``: the
step, parameters, EMA parameters, optimiser state and normaliser), computed from the arrays before the write. Every
load recomputes them for what it read — ``restore`` (training's resume) all five, ``restore_policy`` (``load_policy``:
evaluate, calibrate, export, serve) the step, EMA parameters and normaliser it reads alone — and raises
``CheckpointDamaged`` (one line: step, trees, path) on a mismatch, so damaged files (a bad disk, an interrupted copy,
a sync tool) are never used silently. A checkpoint written before checksums were stored loads with a one-line note
that it is unchecked.
"""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import os
import sys
import typing
from typing import Any, NamedTuple

import jax
import numpy as np
import orbax.checkpoint as ocp

from hipolicy_jax.config import PolicyConfig
from hipolicy_jax.parallel import to_host

# The trees a checkpoint stores, each with its own SHA-256 in meta["checksums"]: the TrainState's fields and the
# normaliser's statistics.
CHECKED_TREES = ("step", "params", "ema_params", "opt_state", "normalizer")


def config_to_dict(cfg) -> dict:
    return dataclasses.asdict(cfg)


def config_from_dict(cls, d: dict):
    """Inverse of ``config_to_dict`` for (nested) frozen config dataclasses; lists become tuples."""
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in d:
            continue
        value, hint = d[f.name], hints[f.name]
        if dataclasses.is_dataclass(hint):
            value = config_from_dict(hint, value)
        elif isinstance(value, list):
            value = _tuple(value)
        kwargs[f.name] = value
    return cls(**kwargs)


def _tuple(v):
    return tuple(_tuple(x) for x in v) if isinstance(v, list) else v


def _identity(path: str) -> tuple[int, int] | None:
    """(device, inode) of a directory, None when it is gone: a directory removed and made again differs."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def tree_sha256(tree) -> str:
    """SHA-256 of a pytree of arrays: every leaf's path, dtype, shape and bytes, in path order. Replicated
    multi-process arrays are read from this process's copy (``parallel.to_host``)."""
    h = hashlib.sha256()
    leaves = jax.tree_util.tree_flatten_with_path(to_host(tree))[0]
    for path, leaf in sorted(leaves, key=lambda kv: jax.tree_util.keystr(kv[0])):
        x = np.ascontiguousarray(np.asarray(leaf))
        h.update(jax.tree_util.keystr(path).encode())
        h.update(f"{x.dtype.str}{x.shape}".encode())
        h.update(x.reshape(-1).view(np.uint8))  # the bytes, without a copy (any dtype, bfloat16 too)
    return h.hexdigest()


def checksums(state, normalizer: dict) -> dict[str, str]:
    """``{tree: SHA-256}`` of a ``TrainState`` and a normaliser's ``to_dict()``, for ``CHECKED_TREES``."""
    return tree_checksums(_named_trees(state, normalizer))


def tree_checksums(trees: dict) -> dict[str, str]:
    """``{name: SHA-256}`` of named trees, hashed on a thread each (hashlib releases the GIL)."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=min(len(trees), os.cpu_count() or 1) or 1) as pool:
        return dict(zip(trees, pool.map(tree_sha256, trees.values())))


def _named_trees(state, normalizer: dict) -> dict:
    return {"step": state.step, "params": state.params, "ema_params": state.ema_params,
            "opt_state": state.opt_state, "normalizer": normalizer}


class CheckpointDamaged(ValueError):
    """A checkpoint's files read back, but one of its trees differs from what was written."""

    def __init__(self, path: str, step: int, trees: tuple[str, ...], hint: str = ""):
        self.path, self.step, self.trees = path, step, tuple(trees)
        super().__init__(f"checkpoint: step {step} at {path} is damaged: {self.what()}{hint}")

    def what(self) -> str:
        """e.g. 'its opt_state does not match the SHA-256 stored when it was written'."""
        verb = "does" if len(self.trees) == 1 else "do"
        return f"its {', '.join(self.trees)} {verb} not match the SHA-256 stored when it was written"

    def with_hint(self, hint: str) -> CheckpointDamaged:
        return CheckpointDamaged(self.path, self.step, self.trees, hint)


def verify(path: str, step: int, meta: dict, trees: dict, *, quiet: bool = False) -> bool:
    """Check restored named trees (``{name: tree}``, names from ``CHECKED_TREES``) against ``meta["checksums"]``;
    → True when checked, False for a checkpoint written before checksums were stored (noted in one line on stderr
    unless ``quiet``). Raises ``CheckpointDamaged`` naming every tree that differs."""
    stored = meta.get("checksums")
    if not stored:
        if not quiet:
            print(f"[checkpoint] step {step} at {path} carries no checksum (written before checksums were stored): "
                  f"loaded unchecked", file=sys.stderr, flush=True)
        return False
    read = tree_checksums(trees)
    damaged = tuple(tree for tree in CHECKED_TREES if tree in read and stored.get(tree) != read[tree])
    if damaged:
        raise CheckpointDamaged(path, step, damaged)
    return True


def quiet_failed_reads() -> None:
    """After a failed orbax read, tensorstore's reads still in flight complete into the asyncio loop orbax has
    closed, and Python reports each as an unraisable "RuntimeError: Event loop is closed" traceback, after the
    one-line error. From the first failed read on, drop exactly those reports (``sys.unraisablehook``; others pass
    through). Idempotent."""
    previous = sys.unraisablehook
    if getattr(previous, "drops_closed_loop", False):
        return

    def hook(report):
        if report.exc_type is RuntimeError and str(report.exc_value) == "Event loop is closed" and \
                report.object is None:
            return
        previous(report)

    hook.drops_closed_loop = True
    sys.unraisablehook = hook


class Checkpointer:
    """Thin wrapper over ``ocp.CheckpointManager``: save every ``every`` steps, keep the newest ``keep``; every
    save stores the trees' checksums in its meta and every ``restore`` verifies them (``verify``)."""

    def __init__(self, directory: str, every: int = 1000, keep: int = 3):
        self.directory = os.path.abspath(directory)
        options = ocp.CheckpointManagerOptions(max_to_keep=keep, save_interval_steps=every, create=True)
        self._mgr = ocp.CheckpointManager(self.directory, options=options)
        self._identity = _identity(self.directory)

    def save(self, step: int, state, normalizer, meta: dict, force: bool = False) -> bool:
        """Save ``step`` when it is due (every ``every`` steps) or ``force``; → whether a save started. The
        checksums are computed here, from the arrays, before orbax writes them."""
        if _identity(self.directory) != self._identity:  # orbax would quietly make it again
            raise FileNotFoundError(errno.ENOENT, f"{self.directory} was removed (or replaced) since this "
                                                  f"checkpointer opened it")
        if not force and not self._mgr.should_save(step):
            return False
        norm = normalizer.to_dict()
        meta = {**meta, "checksums": checksums(state, norm)}
        args = ocp.args.Composite(state=ocp.args.StandardSave(state),
                                  normalizer=ocp.args.StandardSave(norm),
                                  meta=ocp.args.JsonSave(meta))
        return self._mgr.save(step, args=args, force=force)

    def latest_step(self) -> int | None:
        return self._mgr.latest_step()

    def all_steps(self) -> list[int]:
        return list(self._mgr.all_steps())

    def step_path(self, step: int) -> str:
        return os.path.join(self.directory, str(step))

    def restore(self, step: int, abstract_state, *, check: bool = True, quiet: bool = False
                ) -> tuple[Any, dict, dict]:
        """→ (state, normalizer dict, meta), verified against the stored checksums (``check=False`` skips that,
        for the benchmark of its cost only). Raises ``CheckpointDamaged`` when a tree differs."""
        args = ocp.args.Composite(state=ocp.args.StandardRestore(abstract_state),
                                  normalizer=ocp.args.StandardRestore(), meta=ocp.args.JsonRestore())
        r = self._mgr.restore(step, args=args)
        if check:
            verify(self.step_path(step), step, r.meta, _named_trees(r.state, r.normalizer), quiet=quiet)
        return r.state, r.normalizer, r.meta

    def restore_policy(self, step: int, abstract_params, *, check: bool = True, quiet: bool = False
                       ) -> tuple[Any, dict, dict]:
        """→ (EMA parameters, normalizer dict, meta): what a trained policy needs, read alone (orbax's partial
        restore: a quarter of a train state's bytes, no optimiser state) and verified against the stored checksums
        of the step, the EMA parameters and the normaliser (``check=False`` only for the benchmark)."""
        device = jax.sharding.SingleDeviceSharding(jax.devices()[0])
        abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=device),
                                {"step": jax.ShapeDtypeStruct((), np.int32), "ema_params": abstract_params})
        restore_args = ocp.checkpoint_utils.construct_restore_args(abstract)
        state = ocp.args.PyTreeRestore(item=abstract, restore_args=restore_args, partial_restore=True)
        r = self._mgr.restore(step, args=ocp.args.Composite(state=state, normalizer=ocp.args.StandardRestore(),
                                                             meta=ocp.args.JsonRestore()))
        if check:
            verify(self.step_path(step), step, r.meta, {**r.state, "normalizer": r.normalizer}, quiet=quiet)
        return r.state["ema_params"], r.normalizer, r.meta

    def restore_meta(self, step: int) -> dict:
        return self._mgr.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore())).meta

    def wait(self):
        self._mgr.wait_until_finished()

    def close(self):
        self._mgr.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class LoadedPolicy(NamedTuple):
    cfg: PolicyConfig
    net: Any  # PolicyNet
    params: Any  # EMA parameters when EMA was on
    normalizer: Any
    meta: dict
    step: int


def load_policy(directory: str, step: int | None = None) -> LoadedPolicy:
    """Rebuild the network from a checkpoint directory and restore its (EMA) parameters and normaliser."""
    from hipolicy_jax.data.normalizer import Normalizer
    from hipolicy_jax.models.policy_net import PolicyNet, init_policy_params

    if not os.path.isdir(directory):
        raise FileNotFoundError(f"checkpoint: {directory} does not exist")
    with Checkpointer(directory) as ckpt:
        steps = ckpt.all_steps()
        if step is None:
            step = ckpt.latest_step()
        elif step not in steps:
            raise FileNotFoundError(f"checkpoint: no step {step} under {directory} (steps: {sorted(steps)})")
        if step is None:
            raise FileNotFoundError(f"checkpoint: no complete checkpoint under {directory}")
        try:
            meta = ckpt.restore_meta(step)
            cfg = config_from_dict(PolicyConfig, meta["policy"])
            action_dim = int(meta["action_dim"])
            example_obs = {k: np.zeros((1, cfg.chunk.num_freqs, cfg.chunk.obs_horizon, *s), np.float32)
                           for k, s in meta["obs_shapes"].items()}
            net = PolicyNet(cfg, action_dim)
            abstract = jax.eval_shape(lambda: init_policy_params(cfg, action_dim, example_obs, jax.random.key(0)))
            ema_params, norm, meta = ckpt.restore_policy(step, abstract)
        except CheckpointDamaged as e:
            raise e.with_hint(f"; pass another --step (steps: {sorted(steps)}) or re-train") from None
        except Exception as e:  # noqa: BLE001 - any read failure: one line naming the checkpoint
            quiet_failed_reads()
            raise ValueError(f"checkpoint: {os.path.join(directory, str(step))} is unreadable "
                             f"({type(e).__name__}: {str(e).splitlines()[0][:200] if str(e) else ''}); pass "
                             f"another --step or re-train") from e
    return LoadedPolicy(cfg, net, ema_params, Normalizer.from_dict(norm), meta, int(step))


__all__ = ["CHECKED_TREES", "CheckpointDamaged", "Checkpointer", "LoadedPolicy", "checksums", "config_from_dict",
           "config_to_dict", "load_policy", "quiet_failed_reads", "tree_checksums", "tree_sha256", "verify"]
