"""Orbax checkpoints: train state, normaliser and a JSON ``meta`` (configs, shapes, thresholds) per step.

Layout: ``<dir>/<step>/{state, normalizer, meta}``. ``meta`` carries everything needed to rebuild the network
without the training script: the policy config, the action dimension and the per-frame observation shapes.
A checkpoint is only listed by orbax once its write committed, so a run killed mid-write resumes from the
previous complete step.
"""

from __future__ import annotations

import dataclasses
import os
import typing
from typing import Any, NamedTuple

import jax
import numpy as np
import orbax.checkpoint as ocp

from hipolicy_jax.config import PolicyConfig


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


class Checkpointer:
    """Thin wrapper over ``ocp.CheckpointManager``: save every ``every`` steps, keep the newest ``keep``."""

    def __init__(self, directory: str, every: int = 1000, keep: int = 3):
        self.directory = os.path.abspath(directory)
        options = ocp.CheckpointManagerOptions(max_to_keep=keep, save_interval_steps=every, create=True)
        self._mgr = ocp.CheckpointManager(self.directory, options=options)

    def save(self, step: int, state, normalizer, meta: dict, force: bool = False) -> bool:
        args = ocp.args.Composite(state=ocp.args.StandardSave(state),
                                  normalizer=ocp.args.StandardSave(normalizer.to_dict()),
                                  meta=ocp.args.JsonSave(meta))
        return self._mgr.save(step, args=args, force=force)

    def latest_step(self) -> int | None:
        return self._mgr.latest_step()

    def all_steps(self) -> list[int]:
        return list(self._mgr.all_steps())

    def restore(self, step: int, abstract_state) -> tuple[Any, dict, dict]:
        """→ (state, normalizer dict, meta)."""
        args = ocp.args.Composite(state=ocp.args.StandardRestore(abstract_state),
                                  normalizer=ocp.args.StandardRestore(), meta=ocp.args.JsonRestore())
        r = self._mgr.restore(step, args=args)
        return r.state, r.normalizer, r.meta

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
    from hipolicy_jax.training import init_train_state, make_optimizer
    from hipolicy_jax.config import TrainConfig

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
            train_cfg = config_from_dict(TrainConfig, meta["train"])
            action_dim = int(meta["action_dim"])
            example_obs = {k: np.zeros((1, cfg.chunk.num_freqs, cfg.chunk.obs_horizon, *s), np.float32)
                           for k, s in meta["obs_shapes"].items()}
            net = PolicyNet(cfg, action_dim)
            tx = make_optimizer(train_cfg)
            abstract = jax.eval_shape(
                lambda: init_train_state(init_policy_params(cfg, action_dim, example_obs, jax.random.key(0)), tx))
            state, norm, meta = ckpt.restore(step, abstract)
        except Exception as e:  # noqa: BLE001 - any read failure: one line naming the checkpoint
            raise ValueError(f"checkpoint: {os.path.join(directory, str(step))} is unreadable "
                             f"({type(e).__name__}: {str(e).splitlines()[0][:200] if str(e) else ''}); pass "
                             f"another --step or re-train") from e
    return LoadedPolicy(cfg, net, state.ema_params, Normalizer.from_dict(norm), meta, int(step))


__all__ = ["Checkpointer", "LoadedPolicy", "load_policy", "config_to_dict", "config_from_dict"]
