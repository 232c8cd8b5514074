"""Train DP + HiPolicy on an MJX task: ``python -m experiments.train [--task latch_door] [--train.num-steps 500] ...``.

With no arguments: collects (or reuses) 100 expert demos of the default task, trains a CPU-sized HiPolicy on
low-dim state with a progress bar, evaluates periodically with batched MJX rollouts, calibrates the entropy
thresholds on held-out demos, and writes under ``--out`` (default ``runs/<task>_<obs>_seed<seed>``):
``checkpoints/``, ``metrics.jsonl``, ``tb/`` (TensorBoard), ``calibration.json`` and ``summary.json``.
Re-running the same command resumes from the last checkpoint. ``--help`` lists every option.
"""

from __future__ import annotations

import dataclasses
import os
import time

import jax
import numpy as np
import tyro

from experiments.common import (CPU_POLICY, CPU_TRAIN, EvalOptions, build_datasets, calibrate, check_buffer,
                                default_data_path, eval_summary, evaluate_policy, load_or_collect, write_json)
from hipolicy_jax.config import PolicyConfig, TrainConfig, replace
from hipolicy_jax.envs.base import PROPRIO_DIM
from hipolicy_jax.models.policy_net import PolicyNet
from hipolicy_jax.trainer import fit, run_keys


@dataclasses.dataclass(frozen=True)
class TrainArgs:
    task: str = "press_button"
    out: str = ""  # default runs/<task>_<obs_type>_seed<seed>
    data: str = ""  # default data/<task>_<obs keys>[_<camera>]_<episodes>.zarr (collected when missing)
    episodes: int = 100
    val_ratio: float = 0.1
    policy: PolicyConfig = CPU_POLICY
    train: TrainConfig = CPU_TRAIN
    eval: EvalOptions = EvalOptions()
    progress: bool = True
    dry_run: bool = False  # validate config and data, print shapes and parameter count, train nothing
    num_devices: int | None = None  # data-parallel devices (default: all local devices)
    final_eval: bool = True  # evaluate the trained policy at the end (paper tables evaluate on their own: with
    # --eval.every 0 and --no-final-eval nothing is rolled out during training)
    privileged_state: bool = False  # image / point-cloud policies also read the task state (object poses); by default
    # they read proprioception only (policy.encoder.state_dims = 4, as DP / DP3), unless state_dims is set

    def __post_init__(self):
        enc = self.policy.encoder
        if enc.obs_type != "state" and enc.state_dims is None and not self.privileged_state:
            object.__setattr__(self, "policy", replace(self.policy, **{"encoder.state_dims": PROPRIO_DIM}))

    def out_dir(self) -> str:
        return self.out or os.path.join("runs", f"{self.task}_{self.policy.encoder.obs_type}_seed{self.train.seed}")

    def data_path(self) -> str:
        return self.data or default_data_path(self.task, self.policy.encoder, self.episodes)


def dry_run(args: TrainArgs) -> dict:
    """Check the config and the dataset, print what training would see; nothing is trained or written."""
    from hipolicy_jax import parallel
    from hipolicy_jax.data.replay_buffer import ReplayBuffer
    from hipolicy_jax.models.policy_net import init_policy_params, param_count

    path = args.data_path()
    mesh = parallel.make_mesh(args.num_devices)
    parallel.check_batch_size(args.train.batch_size, mesh)
    info = {"task": args.task, "data": path, "devices": 1 if mesh is None else mesh.size}
    if not os.path.exists(path):
        print(f"dataset {path} does not exist: training would first collect {args.episodes} expert demos of "
              f"{args.task}")
        return info
    buffer = ReplayBuffer.load(path)
    check_buffer(buffer, args.policy.encoder, path)
    train_ds, val_ds = build_datasets(buffer, args.policy, args.val_ratio, args.train.seed)
    if len(train_ds) < args.train.batch_size:
        raise ValueError(f"train.batch_size: {args.train.batch_size} exceeds the {len(train_ds)} training windows")
    batch = train_ds.get_batch(np.arange(2))
    action_dim = int(batch["action"].shape[-1])
    abstract = jax.eval_shape(lambda: init_policy_params(args.policy, action_dim, batch["obs"], jax.random.key(0)))
    info.update(episodes=buffer.num_episodes, frames=buffer.num_frames, train_windows=len(train_ds),
                heldout_windows=len(val_ds), param_count=param_count(abstract),
                batch={"action": [args.train.batch_size, *batch["action"].shape[1:]],
                       **{f"obs.{k}": [args.train.batch_size, *v.shape[1:]] for k, v in batch["obs"].items()}})
    for k, v in info.items():
        print(f"{k:>16}: {v}")
    return info


def main(args: TrainArgs) -> dict:
    if args.dry_run:
        return dry_run(args)
    out = args.out_dir()
    os.makedirs(out, exist_ok=True)
    t0 = time.perf_counter()
    buffer = load_or_collect(args.task, args.policy.encoder, args.episodes, args.data_path(),
                             seed=args.train.seed, progress=args.progress)
    train_ds, val_ds = build_datasets(buffer, args.policy, args.val_ratio, args.train.seed)
    print(f"data: {buffer.num_episodes} episodes, {buffer.num_frames} frames; {len(train_ds)} train / "
          f"{len(val_ds)} held-out windows")
    keys = run_keys(args.train.seed)
    cfg = args.policy
    action_dim = int(buffer.data["action"].shape[-1])
    net = PolicyNet(cfg, action_dim)  # a value: equal to the one ``fit`` builds

    last: dict = {}  # the latest in-training evaluation, reused when it ran on the final state

    def eval_fn(state, step):
        # calibration always uses keys["eval"], so at the final step it equals calibration.json's (and
        # experiments.calibrate's); the episodes differ per evaluation step
        params, norm = state.ema_params, train_ds.normalizer
        th, h = calibrate(net, params, norm, cfg, action_dim, val_ds, args.eval, keys["eval"])
        res = evaluate_policy(net, params, norm, cfg, action_dim, args.task, args.eval,
                              jax.random.fold_in(keys["eval"], step), thresholds=th)
        summary = eval_summary(res)
        last.update(step=step, thresholds=th, entropies=h, summary=summary)
        print(f"\n[eval @ {step}] " + ", ".join(f"{k}={v:.3g}" for k, v in summary.items()))
        return summary

    result = fit(cfg, args.train, train_ds, out, eval_fn=eval_fn if (args.eval.every or args.final_eval) else None,
                 eval_every=args.eval.every or None,
                 meta_extra={"task": args.task, "data": os.path.abspath(args.data_path()),
                             "val_ratio": args.val_ratio}, progress=args.progress, num_devices=args.num_devices)
    params, step = result.state.ema_params, int(result.state.step)
    if last.get("step") == step:
        thresholds, entropies, final = last["thresholds"], last["entropies"], last["summary"]
    else:
        thresholds, entropies = calibrate(result.net, params, train_ds.normalizer, cfg, action_dim, val_ds,
                                          args.eval, keys["eval"])
        final = None
        if args.final_eval:
            final = eval_summary(evaluate_policy(result.net, params, train_ds.normalizer, cfg, action_dim,
                                                 args.task, args.eval, jax.random.fold_in(keys["eval"], step),
                                                 thresholds=thresholds))
    write_json(os.path.join(out, "calibration.json"),
               {"thresholds": list(thresholds), "percentiles": list(args.eval.percentiles),
                "num_windows": int(entropies.size), "num_samples": args.eval.num_samples,
                "sampler": args.eval.sampler, "num_steps": args.eval.num_steps,
                "entropy_quantiles": {str(q): float(np.percentile(entropies, q)) for q in (0, 10, 50, 70, 100)}
                if entropies.size else {}})
    summary = {"task": args.task, "steps": int(result.state.step), "param_count": result.meta["param_count"],
               "thresholds": list(thresholds), "eval": final,
               "final_loss": float(np.mean(result.losses[-50:])) if result.losses else None,
               "wall_time_s": time.perf_counter() - t0, "out": os.path.abspath(out)}
    write_json(os.path.join(out, "summary.json"), summary)
    if final is None:
        print(f"\ntrained {summary['steps']} steps; outputs in {out}")
    else:
        print(f"\nsuccess rate {summary['eval']['success_rate']:.2f} over {args.eval.episodes} episodes; "
              f"mean steps (successful) {summary['eval']['mean_steps_success']:.1f}; outputs in {out}")
    return summary


if __name__ == "__main__":
    try:
        main(tyro.cli(TrainArgs))
    except (ValueError, FileNotFoundError, FileExistsError, FloatingPointError) as e:
        raise SystemExit(f"error: {e}")
