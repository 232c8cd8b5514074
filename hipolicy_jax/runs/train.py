"""Train a policy on an MJX task end to end: demos → train / held-out split → ``trainer.fit`` with periodic
evaluation → calibration → outputs in the run directory.

``RunConfig`` is everything one training run needs (``experiments.train`` exposes every field as a flag);
``train(cfg)`` runs it (resuming from the last checkpoint), ``dry_run(cfg)`` validates it, ``ensure_trained(cfg)``
trains only what is unfinished. One ``Evaluator`` serves every evaluation of the run (one compile).

An external task (``--task metaworld:assembly``, ``envs.external``) trains on demos collected in its own venv
(``--data``, default ``data/metaworld_assembly_<episodes>.zarr``), which must exist; it has no MJX env, so training
evaluates nothing (``eval.every`` 0, no final evaluation: ``experiments.evaluate`` runs its episodes in its own
simulator through the policy server) and its thresholds are calibrated on the held-out demos alone.

Action kinds (``ChunkConfig.action_kinds``): a run whose ``policy.chunk.action_kinds`` is None takes them from its
demos (``policy_for_demos``: the buffer's ``action_kinds`` attribute, else the task's: MJX tasks absolute,
Meta-World's ``metaworld`` suite xyz deltas and an absolute gripper) and stores them in the run's config (its
checkpoints' meta) when any is a delta; declared kinds must agree with the demos'. With delta kinds a stride-s
action is a summed delta (``data.windowing.segment_actions``).

Outputs under ``cfg.out_dir()``: ``checkpoints/``, ``metrics.jsonl``, ``tb/``, ``inference.json`` (the inference
settings of its evaluations), ``calibration.json`` and ``summary.json``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import resource
import time

import jax
import numpy as np

from hipolicy_jax.config import (ChunkConfig, EvalConfig, InferenceConfig, ModelConfig, PolicyConfig, TrainConfig,
                                 replace)
from hipolicy_jax import envs, parallel
from hipolicy_jax.data.dataset import train_heldout_datasets
from hipolicy_jax.data.replay_buffer import ReplayBuffer
from hipolicy_jax.data.windowing import resolve_chunk_kinds
from hipolicy_jax.envs.base import PROPRIO_DIM
from hipolicy_jax.envs.demos import check_buffer, check_buffer_fits_env, default_data_path, load_or_collect
from hipolicy_jax.evaluation import calibration
from hipolicy_jax.evaluation.evaluator import Evaluator, eval_summary
from hipolicy_jax.models.policy_net import PolicyNet
from hipolicy_jax.runs.lock import RunLock
from hipolicy_jax.runs.store import Run, eval_key, load_run, read_json, write_inference, write_json
from hipolicy_jax.trainer import fit, logged_train_cpu_seconds, logged_train_seconds, run_keys

# CPU-sized defaults: the paper's windowing (strides 1/2/3, L_h 3, L_c 8) with a small U-Net.
CPU_POLICY = PolicyConfig(chunk=ChunkConfig(), model=ModelConfig(size="cpu"))
CPU_TRAIN = TrainConfig(batch_size=64, num_steps=3000, lr=3e-4, warmup_steps=200, log_every=50, ckpt_every=500)
# On a CPU: few samples and DDIM steps; the paper used N=100 and 100 DDPM steps.
CPU_INFERENCE = InferenceConfig(num_samples=16, sampler="auto", num_steps=None)


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """One training run: task, data, policy, training, evaluation and inference settings, output directory."""

    task: str = "press_button"
    out: str = ""  # default runs/<task>_<obs_type>_seed<seed>
    data: str = ""  # default data/<task>_<obs keys>[_<camera>]_<episodes>.zarr (collected when missing)
    episodes: int = 100  # expert demos to collect (when --data does not exist)
    demo_seed: int = 0  # seed of that collection: the buffer's path has no training seed, so every seed shares it
    val_ratio: float = 0.1  # held-out demo episodes (threshold calibration)
    policy: PolicyConfig = CPU_POLICY
    train: TrainConfig = CPU_TRAIN
    eval: EvalConfig = EvalConfig()
    inference: InferenceConfig = CPU_INFERENCE
    progress: bool = True
    dry_run: bool = False  # validate config and data, print shapes and parameter count, train nothing
    num_devices: int | None = None  # data-parallel devices (default: all local devices)
    final_eval: bool = True  # evaluate the trained policy at the end (paper tables evaluate on their own: with
    # --eval.every 0 and --no-final-eval nothing is rolled out during training; external tasks never are)
    privileged_state: bool = False  # image / point-cloud policies also read the task state (object poses); by default
    # they read proprioception only (policy.encoder.state_dims = 4, as DP / DP3), unless state_dims is set

    def __post_init__(self):
        envs.check_task(self.task)
        if self.external:  # no MJX env to roll out in: training evaluates nothing, experiments.evaluate does
            if self.eval.every not in (0, EvalConfig.every):
                raise ValueError(f"eval.every: {self.task} has no MJX env to evaluate in during training (it is "
                                 f"evaluated in its own simulator through the policy server: python -m "
                                 f"experiments.evaluate --checkpoint RUN_DIR); pass --eval.every 0, got "
                                 f"{self.eval.every}")
            object.__setattr__(self, "eval", dataclasses.replace(self.eval, every=0))
            object.__setattr__(self, "final_eval", False)
        half = self.policy.chunk.chunk_len // 2
        if self.inference.delay > half:  # the decision must be ready before the next one starts
            raise ValueError(f"inference.delay: at most chunk.chunk_len // 2 = {half} control steps (a decision "
                             f"must be ready before the next one starts), got {self.inference.delay}")
        enc = self.policy.encoder
        if enc.obs_type != "state" and enc.state_dims is None and not self.privileged_state:
            proprio = envs.external.make(self.task).suite.proprio_dim if self.external else PROPRIO_DIM
            object.__setattr__(self, "policy", replace(self.policy, **{"encoder.state_dims": proprio}))

    @property
    def external(self) -> bool:
        """Whether the task is an external one (no MJX env; demos from its own venv)."""
        return envs.external.is_external(self.task)

    def out_dir(self) -> str:
        task = self.task.replace(":", "_")
        return self.out or os.path.join("runs", f"{task}_{self.policy.encoder.obs_type}_seed{self.train.seed}")

    def data_path(self) -> str:
        if self.data:
            return self.data
        if self.external:
            return envs.external.default_data_path(self.task, self.episodes)
        return default_data_path(self.task, self.policy.encoder, self.episodes)

    def task_spec(self):
        """What the run's demos must fit (action and observation shapes): the MJX env, or the external task."""
        if self.external:
            return envs.external.make(self.task, self.policy.encoder)
        return envs.make_for_encoder(self.task, self.policy.encoder)


def policy_for_demos(cfg: RunConfig, buffer: ReplayBuffer, env) -> PolicyConfig:
    """``cfg.policy`` with its ``chunk.action_kinds`` settled against the demos (``windowing.resolve_chunk_kinds``):
    the buffer's recorded kinds, else the task's (``env.action_kinds``); what the run trains and stores."""
    chunk = resolve_chunk_kinds(cfg.policy.chunk, buffer.action_kinds, getattr(env, "action_kinds", None),
                                int(buffer.data["action"].shape[-1]), f"the buffer {cfg.data_path()}")
    return cfg.policy if chunk == cfg.policy.chunk else dataclasses.replace(cfg.policy, chunk=chunk)


def same_policy(stored: PolicyConfig, cfg: PolicyConfig) -> bool:
    """Whether a run trained with ``stored`` is the run ``cfg`` asks for: equal, or equal but for the action kinds
    the run took from its demos where ``cfg`` leaves them None."""
    if cfg.chunk.action_kinds is None:
        cfg = replace(cfg, **{"chunk.action_kinds": stored.chunk.action_kinds})
    return stored == cfg


def load_external_demos(cfg: RunConfig) -> ReplayBuffer:
    """An external task's demo buffer at ``cfg.data_path()``, checked against the encoder and the task (it is never
    collected here: a missing one is an error naming the commands that make it)."""
    path = cfg.data_path()
    if not os.path.exists(path):
        raise FileNotFoundError(f"data: {path} does not exist; {cfg.task} demos are collected in their own venv: "
                                f"{envs.external.collect_hint(cfg.task, cfg.episodes, path)} (or pass --data)")
    envs.external.check_demos(cfg.task, path)
    buffer = ReplayBuffer.load(path)
    check_buffer(buffer, cfg.policy.encoder, path)
    return buffer


class DemoCalibrator(Evaluator):
    """The calibration half of an ``Evaluator`` for a task with no MJX env (external tasks): entropy thresholds from
    held-out demo windows through the same sampler; it cannot roll out."""

    def __init__(self, task: str, cfg: PolicyConfig, action_dim: int, inference: InferenceConfig = InferenceConfig()):
        self.cfg, self.action_dim, self.inference = cfg, action_dim, inference
        self.task, self.env = task, None
        self.net = PolicyNet(cfg, action_dim)
        self._sampler = None

    @property
    def traces(self) -> int:
        return 0

    def rollout(self, *args, **kwargs):
        raise ValueError(f"{self.task} has no MJX env to roll out in; evaluate it in its own simulator")


def dry_run(cfg: RunConfig) -> dict:
    """Check the config and the dataset, print what training would see; nothing is trained or written."""
    from hipolicy_jax import parallel
    from hipolicy_jax.models.policy_net import init_policy_params, param_count

    path = cfg.data_path()
    mesh = parallel.make_mesh(cfg.num_devices)
    parallel.check_batch_size(cfg.train.batch_size, mesh)
    info = {"task": cfg.task, "data": path, "devices": 1 if mesh is None else mesh.size}
    if cfg.external:
        buffer = load_external_demos(cfg)
    elif not os.path.exists(path):
        print(f"dataset {path} does not exist: training would first collect {cfg.episodes} expert demos of "
              f"{cfg.task}")
        return info
    else:
        buffer = ReplayBuffer.load(path)
        check_buffer(buffer, cfg.policy.encoder, path)
    env = cfg.task_spec()
    check_buffer_fits_env(buffer, env, path)
    policy = policy_for_demos(cfg, buffer, env)
    train_ds, val_ds = train_heldout_datasets(buffer, policy.chunk, policy.encoder.obs_keys, cfg.val_ratio,
                                              cfg.train.seed, max_action_pad=cfg.train.max_action_pad)
    if len(train_ds) < cfg.train.batch_size:
        raise ValueError(f"train.batch_size: {cfg.train.batch_size} exceeds the {len(train_ds)} training windows")
    batch = train_ds.get_batch(np.arange(2))
    action_dim = int(batch["action"].shape[-1])
    abstract = jax.eval_shape(lambda: init_policy_params(policy, action_dim, batch["obs"], jax.random.key(0)))
    info.update(action_kinds=list(policy.chunk.kinds(action_dim)))
    info.update(episodes=buffer.num_episodes, frames=buffer.num_frames, train_windows=len(train_ds),
                heldout_windows=len(val_ds), param_count=param_count(abstract),
                batch={"action": [cfg.train.batch_size, *batch["action"].shape[1:]],
                       **{f"obs.{k}": [cfg.train.batch_size, *v.shape[1:]] for k, v in batch["obs"].items()}})
    for k, v in info.items():
        print(f"{k:>16}: {v}")
    return info


def cpu_cores() -> int:
    """The CPU cores this process may run on (its affinity: ``taskset -c 0`` → 1): wall time × this bounds the
    CPU-seconds it used from above (other jobs on those cores count too)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def cpu_seconds() -> float:
    """CPU seconds this process used so far (every thread, user + system) plus those of its finished child
    processes (an external task's bridge): the difference over a span is what the span cost, whatever else ran
    on the same cores."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


def _plus(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None else a + b


def prepare_out_dir(out: str) -> str:
    """Create the run directory; a path that is a file or not writable is a one-line ``ValueError``."""
    if os.path.exists(out) and not os.path.isdir(out):
        raise ValueError(f"out: {out} is a file; pass a directory for the run (--out)")
    try:
        os.makedirs(out, exist_ok=True)
    except OSError as e:
        raise ValueError(f"out: cannot create the run directory {out} ({e.strerror}); pass another --out") from e
    if not os.access(out, os.W_OK | os.X_OK):
        raise ValueError(f"out: the run directory {out} is not writable; pass another --out")
    return out


def train(cfg: RunConfig) -> dict:
    """Train (or resume) the run, calibrate its thresholds, evaluate it; → the summary written to summary.json.

    The run directory is locked while this runs (``lock.RunLock``: a second training on it refuses). SIGINT /
    SIGTERM stop after the current step with a checkpoint written (``trainer.TrainingInterrupted``).

    In a multi-process run (``parallel.initialize_distributed``) every process trains its share of each batch;
    process 0 alone holds the lock, collects missing demos, evaluates (on its own devices) and writes the run's
    files; the others return ``{"steps", "process"}``."""
    out = prepare_out_dir(cfg.out_dir())
    with RunLock(out) if parallel.is_primary() else contextlib.nullcontext():
        return _train(cfg, out)


def _train(cfg: RunConfig, out: str) -> dict:
    t0, c0 = time.perf_counter(), cpu_seconds()
    primary = parallel.is_primary()
    if primary and not cfg.external:
        load_or_collect(cfg.task, cfg.policy.encoder, cfg.episodes, cfg.data_path(), seed=cfg.demo_seed,
                        progress=cfg.progress)
    parallel.barrier("demos")  # the others read the demos process 0 wrote
    if cfg.external:
        buffer = load_external_demos(cfg)
    else:
        buffer = load_or_collect(cfg.task, cfg.policy.encoder, cfg.episodes, cfg.data_path(), seed=cfg.demo_seed,
                                 progress=False)
    env = cfg.task_spec()
    check_buffer_fits_env(buffer, env, cfg.data_path())  # before any training: the run is evaluated in this env
    policy = policy_for_demos(cfg, buffer, env)  # the demos' action kinds where cfg leaves them None
    train_ds, val_ds = train_heldout_datasets(buffer, policy.chunk, policy.encoder.obs_keys, cfg.val_ratio,
                                              cfg.train.seed, max_action_pad=cfg.train.max_action_pad)
    print(f"data: {buffer.num_episodes} episodes, {buffer.num_frames} frames; {len(train_ds)} train / "
          f"{len(val_ds)} held-out windows")
    keys = run_keys(cfg.train.seed)
    action_dim = int(buffer.data["action"].shape[-1])
    if cfg.external:
        evaluator = DemoCalibrator(cfg.task, policy, action_dim, cfg.inference)
    else:
        evaluator = Evaluator(env, policy, action_dim, cfg.inference)
    if primary:
        write_inference(out, cfg.inference)
    last: dict = {}  # the latest in-training evaluation, reused when it ran on the final state

    def calibrate(params):
        # always keys["eval"]: at the final step this equals calibration.json's (and experiments.calibrate's)
        return evaluator.calibrate(params, train_ds.normalizer, val_ds, keys["eval"])

    def evaluate(params, thresholds):
        # every evaluation of the run starts from the same initial states (eval_key of the training seed), so
        # checkpoints compare on equal terms and experiments.evaluate's defaults reproduce the final numbers
        return eval_summary(evaluator.evaluate(params, train_ds.normalizer, cfg.eval.episodes,
                                               eval_key(cfg.train.seed), thresholds))

    def local(params):
        # evaluation runs on process 0's devices alone: a multi-process state is brought to its host first
        return params if jax.process_count() == 1 else parallel.to_host(params)

    def eval_fn(state, step):
        params = local(state.ema_params)
        thresholds, entropies = calibrate(params)
        summary = evaluate(params, thresholds)
        last.update(step=step, thresholds=thresholds, entropies=entropies, summary=summary)
        print(f"\n[eval @ {step}] " + ", ".join(f"{k}={v:.3g}" for k, v in summary.items()))
        return summary

    evaluating = (cfg.eval.every or cfg.final_eval) and primary
    result = fit(policy, cfg.train, train_ds, out, eval_fn=eval_fn if evaluating else None,
                 eval_every=cfg.eval.every or None,
                 meta_extra={"task": cfg.task, "data": os.path.abspath(cfg.data_path()), "val_ratio": cfg.val_ratio},
                 progress=cfg.progress, num_devices=cfg.num_devices)
    step = int(parallel.to_host(result.state.step))
    if not primary:
        return {"steps": step, "process": jax.process_index()}
    params = local(result.state.ema_params)
    if last.get("step") == step:
        thresholds, entropies, final = last["thresholds"], last["entropies"], last["summary"]
    else:
        thresholds, entropies = calibrate(params)
        final = evaluate(params, thresholds) if cfg.final_eval else None
    calibration.write_calibration(
        calibration.calibration_record(entropies, thresholds, policy.chunk.num_freqs, cfg.inference,
                                       source="demos", seed=cfg.train.seed, checkpoint_step=step, task=cfg.task),
        os.path.join(out, calibration.CALIBRATION_FILE))
    summary = {"task": cfg.task, "steps": step, "param_count": result.meta["param_count"],
               "thresholds": list(thresholds), "eval": final, "eval_episodes": cfg.eval.episodes,
               "eval_seed": cfg.train.seed,
               "final_loss": float(np.mean(result.losses[-50:])) if result.losses else None,
               # this session's wall time + the logged step time of the sessions before a resume
               "wall_time_s": time.perf_counter() - t0 + logged_train_seconds(out, result.start_step),
               # process CPU time, the same span (None when an earlier session predates its measurement)
               "cpu_time_s": _plus(cpu_seconds() - c0, logged_train_cpu_seconds(out, result.start_step)),
               "cpu_cores": cpu_cores(), "out": os.path.abspath(out),
               "demos": {"episodes": buffer.num_episodes, "frames": buffer.num_frames}}
    write_json(os.path.join(out, "summary.json"), summary)
    if final is None:
        print(f"\ntrained {summary['steps']} steps; outputs in {out}"
              + (f"\nevaluate it: python -m experiments.evaluate --checkpoint {out}" if cfg.external else ""))
    else:
        print(f"\nsuccess rate {final['success_rate']:.2f} over {cfg.eval.episodes} episodes; mean steps "
              f"(successful) {final['mean_steps_success']:.1f}; outputs in {out}")
    return summary


def main(cfg: RunConfig) -> dict:
    """``dry_run`` or ``train``, as ``cfg.dry_run`` says."""
    return dry_run(cfg) if cfg.dry_run else train(cfg)


def finished(cfg: RunConfig) -> bool:
    """Whether the run directory holds a run trained to ``cfg.train.num_steps`` (its summary.json says so)."""
    summary = os.path.join(cfg.out_dir(), "summary.json")
    return os.path.exists(summary) and read_json(summary).get("steps") == cfg.train.num_steps


def ensure_trained(cfg: RunConfig) -> Run:
    """Train (or resume) a run unless it finished already; → the loaded run. A finished run is reused whatever
    inference settings ``cfg`` has; a run of another policy config in the same directory is refused."""
    out = cfg.out_dir()
    if not finished(cfg):
        print(f"[runs] training {out}", flush=True)
        train(cfg)
    run = load_run(out)
    if not same_policy(run.policy.cfg, cfg.policy):
        raise ValueError(f"{out} holds a run of a different policy config; delete it or pass another --runs")
    return run
