"""Pieces shared by the experiment entry points: CPU defaults, demo data, datasets, evaluation, calibration.

The flow every script follows: demos (collected once, cached as a zarr ReplayBuffer) → train / held-out datasets
→ ``trainer.fit`` → thresholds calibrated on held-out demos → batched MJX rollouts of the policy.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
from typing import Literal, NamedTuple

import jax
import numpy as np

from hipolicy_jax.config import (ChunkConfig, DiffusionConfig, EncoderConfig, ModelConfig, PolicyConfig,
                                 SamplingConfig, TrainConfig)
from hipolicy_jax.data.dataset import SequenceDataset, split_episodes
from hipolicy_jax.data.replay_buffer import ReplayBuffer
from hipolicy_jax.policy import PolicyArgs, calibrate_thresholds, make_policy_fn, measure_entropies, policy_obs_keys

# CPU-sized defaults: the paper's windowing (strides 1/2/3, L_h 3, L_c 8) with a small U-Net.
CPU_POLICY = PolicyConfig(chunk=ChunkConfig(), model=ModelConfig(size="cpu"), diffusion=DiffusionConfig(),
                          sampling=SamplingConfig(num_samples=16))
CPU_TRAIN = TrainConfig(batch_size=64, num_steps=3000, lr=3e-4, warmup_steps=200, log_every=50, ckpt_every=500)

# Which tasks need tight end-effector tolerances (the paper's precise / non-precise split); the one place it lives.
TASK_PRECISE: dict[str, bool] = {"press_button": True, "stack_cubes": True, "latch_door": False, "pick_place": False}

# Salt of the evaluation key: rollouts use fold_in(key(seed), EVAL_SALT), so their initial states never coincide
# with those of the demos collected from key(seed).
EVAL_SALT = 0x5EED


@dataclasses.dataclass(frozen=True)
class EvalOptions:
    """Batched-rollout evaluation. On a CPU use few samples and DDIM steps; the paper used N=100, 100 DDPM steps."""

    episodes: int = 20
    num_samples: int = 16  # N for the entropy estimate
    sampler: Literal["ddpm", "ddim"] = "ddim"
    num_steps: int = 10
    every: int = 1000  # training steps between evaluations (0: only at the end)
    entropy_guided: bool = True  # False: always execute the highest frequency
    percentiles: tuple[float, ...] = (10.0, 70.0)  # threshold calibration on held-out demos
    calib_windows: int = 128


def policy_env_kwargs(encoder: EncoderConfig) -> dict:
    """Env settings (``envs.make`` / ``collect_demos`` keywords) for a policy with this encoder: the ``obs_keys`` it
    reads and, for vision, the ``camera`` (``envs.camera.CameraConfig``): images of ``image_size`` pixels square, or
    ``num_points`` points (with rgb when ``point_dims == 6``) cast from the default camera resolution."""
    from hipolicy_jax.envs.camera import CameraConfig

    kwargs: dict = {"obs_keys": policy_obs_keys(encoder)}
    if encoder.obs_type == "image":
        kwargs["camera"] = CameraConfig(height=encoder.image_size, width=encoder.image_size)
    elif encoder.obs_type == "pointcloud":
        kwargs["camera"] = CameraConfig(num_points=encoder.num_points, point_rgb=encoder.point_dims == 6)
    return kwargs


def default_data_path(task: str, encoder: EncoderConfig, episodes: int) -> str:
    """``data/<task>_<obs keys>[_<camera>]_<episodes>.zarr``: the camera part (``84px``, ``512pts``, ``512pts-rgb``)
    appears for image and point-cloud encoders, so buffers of different resolutions never collide."""
    keys = policy_obs_keys(encoder)
    cam = {"state": "", "image": f"_{encoder.image_size}px",
           "pointcloud": f"_{encoder.num_points}pts" + ("-rgb" if encoder.point_dims == 6 else "")}[encoder.obs_type]
    return os.path.join("data", f"{task}_{'-'.join(keys)}{cam}_{episodes}.zarr")


# Which config field sets each camera key's per-frame shape (for error messages).
_FRAME_FIELDS = {"image": "policy.encoder.image_size", "point_cloud": "policy.encoder.num_points / point_dims"}


def check_buffer(buffer: ReplayBuffer, encoder: EncoderConfig, path: str) -> None:
    """Raise ``ValueError`` naming the key, the expected and the actual per-frame shape if ``buffer`` lacks a key
    the encoder reads or holds images / point clouds of another size than the encoder's."""
    keys = policy_obs_keys(encoder)
    missing = [k for k in (*keys, "action") if k not in buffer.data]
    if missing:
        raise ValueError(f"{path}: lacks keys {missing} (has {sorted(buffer.data)}); collect with those obs")
    expected = {"image": (encoder.image_size, encoder.image_size, 3),
                "point_cloud": (encoder.num_points, encoder.point_dims)}
    for key in keys:
        if key in expected and tuple(buffer.data[key].shape[1:]) != expected[key]:
            raise ValueError(f"{path}: data/{key} has frames of shape {tuple(buffer.data[key].shape[1:])}, the "
                             f"encoder expects {expected[key]}; set {_FRAME_FIELDS[key]} to match, or pass another "
                             f"--data (a missing one is collected with the encoder's camera)")


def load_or_collect(task: str, encoder: EncoderConfig, episodes: int, path: str, seed: int = 0,
                    progress: bool = True) -> ReplayBuffer:
    """Reuse the dataset at ``path`` (checked against ``encoder``: keys and frame shapes) or collect ``episodes``
    expert demos of ``task`` with the encoder's observations and camera (``policy_env_kwargs``) and save them."""
    if os.path.exists(path):
        buffer = ReplayBuffer.load(path)
        check_buffer(buffer, encoder, path)
        return buffer
    from hipolicy_jax.envs.demos import collect_demos

    if progress:
        print(f"collecting {episodes} expert demos of {task} → {path}")
    episodes_data = collect_demos(task, episodes, jax.random.key(seed), **policy_env_kwargs(encoder))
    buffer = ReplayBuffer.from_episodes(episodes_data)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    buffer.save(path)
    return buffer


def build_datasets(buffer: ReplayBuffer, cfg: PolicyConfig, val_ratio: float, seed: int):
    """Train / held-out datasets split by episode; the held-out one reuses the training normaliser."""
    keys = policy_obs_keys(cfg.encoder)
    train_mask, val_mask = split_episodes(buffer.num_episodes, val_ratio, seed)
    train = SequenceDataset(buffer, cfg.chunk, obs_keys=keys, episode_mask=train_mask)
    val = SequenceDataset(buffer, cfg.chunk, obs_keys=keys, episode_mask=val_mask, normalizer=train.normalizer)
    return train, val


def calibrate(net, params, normalizer, cfg: PolicyConfig, action_dim: int, val_ds, opts: EvalOptions,
              key) -> tuple[tuple[float, ...], np.ndarray]:
    """Thresholds at ``opts.percentiles`` of the held-out demos' action entropies → (thresholds, entropies)."""
    m = cfg.chunk.num_freqs
    if m == 1:
        return (-math.inf, math.inf), np.zeros(0)
    h = measure_entropies(net, params, normalizer, cfg, action_dim, val_ds, key, max_windows=opts.calib_windows,
                          num_samples=opts.num_samples, num_steps=opts.num_steps, sampler=opts.sampler)
    pct = opts.percentiles if len(opts.percentiles) == m - 1 else None
    return calibrate_thresholds(h, m, pct), h


def evaluate_policy(net, params, normalizer, cfg: PolicyConfig, action_dim: int, task: str, opts: EvalOptions,
                    key, thresholds=None):
    """Roll the policy out on ``opts.episodes`` episodes in one compiled call → ``envs.rollout.EvalResult``."""
    from hipolicy_jax.envs.rollout import evaluate

    th = thresholds if (opts.entropy_guided and thresholds is not None) else None
    policy_fn = make_policy_fn(net, cfg, action_dim, num_samples=opts.num_samples, num_steps=opts.num_steps,
                               sampler=opts.sampler)
    args = PolicyArgs(params, normalizer, None if th is None else np.asarray(th, np.float32))
    return evaluate(policy_fn, policy_env(task, cfg.encoder), opts.episodes, key,
                    history_len=cfg.chunk.obs_span, chunk_len=cfg.chunk.chunk_len, policy_args=args)


def eval_summary(result) -> dict:
    """JSON-able scalars of an ``EvalResult``."""
    valid = np.asarray(result.valid)
    strides = np.asarray(result.stride)[valid]
    out = {"success_rate": float(result.success_rate), "mean_steps_success": float(result.mean_steps_success),
           "mean_steps": float(np.mean(np.asarray(result.steps)))}
    for s in np.unique(strides):
        out[f"stride{int(s)}_frac"] = float(np.mean(strides == s))
    ent = np.asarray(result.entropy)[valid]
    if ent.size and np.isfinite(ent).any():
        out["mean_entropy"] = float(np.nanmean(ent))
    return out


def write_json(path: str, obj) -> None:
    with open(path, "w") as f:
        json.dump(obj, f, indent=2, default=float)


@functools.lru_cache(maxsize=16)
def policy_env(task: str, encoder: EncoderConfig = EncoderConfig()):
    """The task's env computing what ``encoder`` reads, with its camera (``policy_env_kwargs``); one instance per
    setting, so compiled rollouts stay cached."""
    from hipolicy_jax import envs

    return envs.make(task, **policy_env_kwargs(encoder))


def eval_key(seed: int) -> jax.Array:
    """Evaluation PRNG key of a seed, disjoint from the demo-collection key ``key(seed)``."""
    return jax.random.fold_in(jax.random.key(seed), EVAL_SALT)


def guidance_thresholds(thresholds, num_freqs: int, entropy_guided: bool = True) -> np.ndarray:
    """(M+1,) float32 thresholds to trace into a rollout. Without entropy guidance every finite entropy selects the
    highest frequency: (-inf, +inf, ..., +inf). Passing thresholds as an array either way keeps one compiled
    rollout for both evaluations (``None`` would change the traced structure and recompile)."""
    if not entropy_guided or thresholds is None or num_freqs == 1:
        return np.array([-np.inf] + [np.inf] * num_freqs, np.float32)
    th = np.asarray(thresholds, np.float32)
    if th.shape != (num_freqs + 1,):
        raise ValueError(f"thresholds: need M+1={num_freqs + 1} values for M={num_freqs}, got {th.tolist()}")
    return th


def evaluate_policy_recorded(net, params, normalizer, cfg: PolicyConfig, action_dim: int, task: str,
                             opts: EvalOptions, key, thresholds=None):
    """``evaluate_policy`` that also returns the rollout's ``envs.rollout.Recording`` (qpos for videos), from the
    same compiled rollout. Thresholds go through ``guidance_thresholds(thresholds, M, opts.entropy_guided)``."""
    from hipolicy_jax.envs import rollout

    policy_fn = make_policy_fn(net, cfg, action_dim, num_samples=opts.num_samples, num_steps=opts.num_steps,
                               sampler=opts.sampler)
    th = guidance_thresholds(thresholds, cfg.chunk.num_freqs, opts.entropy_guided)
    stateful, init_fn = rollout.stateless(policy_fn, with_args=True)
    return rollout.rollout_episodes(stateful, init_fn, policy_env(task, cfg.encoder),
                                    opts.episodes, key, history_len=cfg.chunk.obs_span,
                                    chunk_len=cfg.chunk.chunk_len, policy_args=PolicyArgs(params, normalizer, th))


class Run(NamedTuple):
    """A trained run: its output dir (summary, calibration, eval/), checkpoint dir, loaded policy and task."""

    run_dir: str
    ckpt_dir: str
    policy: object  # hipolicy_jax.checkpoint.LoadedPolicy
    task: str


def resolve_run(path: str) -> tuple[str, str]:
    """(run_dir, checkpoint_dir) from a train output dir (holding ``checkpoints/``) or the checkpoints dir itself."""
    path = os.path.abspath(path)
    if os.path.isdir(os.path.join(path, "checkpoints")):
        return path, os.path.join(path, "checkpoints")
    if os.path.isdir(path) and any(d.isdigit() for d in os.listdir(path)):
        return os.path.dirname(path), path
    raise FileNotFoundError(f"checkpoint: {path} is neither a run dir holding checkpoints/ nor a checkpoints dir")


def load_run(path: str, step: int | None = None) -> Run:
    """Load the (EMA) policy of a run dir or checkpoints dir; the task comes from the checkpoint's meta."""
    from hipolicy_jax.checkpoint import load_policy

    run_dir, ckpt_dir = resolve_run(path)
    loaded = load_policy(ckpt_dir, step)
    # orbax restores device-committed arrays; jit keys its cache on commitment, so an uncommitted copy lets the
    # evaluation reuse a rollout compiled for the training state (same process) instead of compiling it again
    uncommitted = functools.partial(jax.tree.map, lambda x: jax.device_put(np.asarray(x)))
    loaded = loaded._replace(params=uncommitted(loaded.params), normalizer=uncommitted(loaded.normalizer))
    if "task" not in loaded.meta:
        raise ValueError(f"{ckpt_dir}: checkpoint meta lacks 'task' (not written by experiments.train?)")
    return Run(run_dir, ckpt_dir, loaded, str(loaded.meta["task"]))


def run_action_dim(run: Run) -> int:
    return int(run.policy.meta["action_dim"])


def read_calibration(run_dir: str) -> dict | None:
    """The run's ``calibration.json`` (None when absent)."""
    path = os.path.join(run_dir, "calibration.json")
    if not os.path.exists(path):
        return None
    with open(path) as f:
        return json.load(f)


def read_json(path: str):
    with open(path) as f:
        return json.load(f)
