"""Experiment budgets and the run layout of the paper tables: a budget fixes the policy, training, evaluation and
inference settings (``smoke`` / ``cpu`` / ``gpu``), a variant is a set of config changes on top of it, and every run
lives at ``<runs>/<budget>/<task>/<obs>/<variant>/seed<k>``. ``experiments.paper`` builds its tables from these and
``benchmarks`` find their runs with them.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any, NamedTuple

from hipolicy_jax.config import EvalConfig, InferenceConfig, ModelConfig, PolicyConfig, TrainConfig, replace
from hipolicy_jax.envs import external
from hipolicy_jax.envs.base import PROPRIO_DIM
from hipolicy_jax.envs.demos import default_data_path
from hipolicy_jax.runs.train import CPU_POLICY, CPU_TRAIN, RunConfig


class Budget(NamedTuple):
    """Everything a budget fixes: policy / training configs, demos, evaluation episodes and inference settings."""

    policy: PolicyConfig
    train: TrainConfig
    eval: EvalConfig
    inference: InferenceConfig
    demos: int
    val_ratio: float
    note: str
    checkpoints: int = 0  # > 0: that many evenly spaced checkpoints kept per run (num_steps / checkpoints apart)
    periodic_episodes: int = 0  # > 0: every kept checkpoint evaluated on that many episodes (DP3's metric)


BUDGETS: dict[str, Budget] = {
    "smoke": Budget(
        policy=PolicyConfig(model=ModelConfig(size="tiny", fusion_heads=2)),
        train=TrainConfig(batch_size=16, num_steps=12, warmup_steps=2, log_every=6, ckpt_every=6),
        eval=EvalConfig(episodes=3, every=0),
        inference=InferenceConfig(num_samples=4, sampler="auto", num_steps=2, calib_windows=16),
        demos=6, val_ratio=0.34, periodic_episodes=2,  # (external tasks only: the kept checkpoints, 2 episodes)
        note="tiny model, 12 steps x batch 16 on 6 demos; 3 episodes, N=4, DDIM 2 steps"),
    "cpu": Budget(
        policy=CPU_POLICY,
        train=dataclasses.replace(CPU_TRAIN, num_steps=2000),
        eval=EvalConfig(episodes=100, every=0),
        inference=InferenceConfig(num_samples=16, sampler="auto", num_steps=10, calib_windows=128),
        demos=100, val_ratio=0.1, note="CPU model, 2000 steps x batch 64 on 100 demos; 100 episodes, N=16, DDIM 10"),
    "gpu": Budget(
        policy=PolicyConfig(model=ModelConfig(size="paper")),
        train=TrainConfig(batch_size=128, num_steps=20000, lr=1e-4, warmup_steps=500, log_every=100,
                          ckpt_every=2000),
        eval=EvalConfig(episodes=100, every=0),
        inference=InferenceConfig(num_samples=100, sampler="ddpm", calib_windows=256),
        demos=100, val_ratio=0.1,
        note="paper-size model, 20000 steps x batch 128 on 100 demos; 100 episodes, N=100, DDPM 100 steps"),
    # Meta-World (results/metaworld/PROTOCOL.md): the cpu budget's network and optimiser on 11 expert demos (one
    # held out per run), 100 episodes through the policy server; the training length is the pilot's T
    # (METAWORLD_STEPS), 10 checkpoints kept, each evaluated on 20 episodes for DP3's metric
    "metaworld": Budget(
        policy=CPU_POLICY,
        train=dataclasses.replace(CPU_TRAIN, num_steps=8000),
        eval=EvalConfig(episodes=100, every=0),
        inference=InferenceConfig(num_samples=16, sampler="auto", num_steps=10, calib_windows=128),
        demos=11, val_ratio=0.1, checkpoints=10, periodic_episodes=20,
        note="CPU model, the pilot's T steps x batch 64 on 10 demos (+1 held out); 100 episodes through the policy "
             "server, N=16, DDIM 10; 10 checkpoints x 20 episodes for DP3's metric"),
}
# The Meta-World training length T, fixed by the DP pilot (results/metaworld/PROTOCOL.md "Pilot entries"); None until
# the pilot has chosen it (the campaign refuses to start the table's runs before).
METAWORLD_STEPS: int | None = 4000  # the pilot of 2026-12-05: T = 8000, rule 1 lowered it to 4000
# The budget rules' task counts (PROTOCOL.md "Budget" rules 1 and 2, fixed after the pilot): the state columns run on
# the first METAWORLD_STATE_TASKS of the protocol's task order (None: all 16), the point-cloud columns on the first
# METAWORLD_POINTCLOUD_TASKS (None: none yet).
METAWORLD_STATE_TASKS: int | None = 10  # the pilot entry of 2026-12-05 (rule 1)
METAWORLD_POINTCLOUD_TASKS: int | None = 0  # the pilot entry of 2026-12-05 (rule 2: none fits)
# Amendment 2 (results/metaworld/PROTOCOL.md; campaigns.metaworld_amendment2), fixed by the dated entry that follows
# its pilot (`python -m experiments.metaworld pilot2`); None until then (its main runs refuse to start before):
# the plateau rule's fraction f of T_task, the budget rule's arm-A task count K (the first K of its five tasks) and
# arm B's task count (the first of arm A's list that fit 20 CPU-hours).
METAWORLD_A2_FRACTION: float | None = 0.25  # the pilot entry of 2026-12-07 (plateau rule)
METAWORLD_A2_TASKS: int | None = 5  # the pilot entry of 2026-12-07 (budget rule: all five fit)
METAWORLD_A2_B_TASKS: int | None = None
# The Meta-World pilot: DP, seed 0, 8000 steps with checkpoints at 1000 / 2000 / 4000 / 8000 evaluated.
METAWORLD_PILOT = {"train.num_steps": 8000, "train.ckpt_every": 1000}
METAWORLD_PILOT_STEPS = (1000, 2000, 4000, 8000)

# Config changes per observation type. Vision policies read proprioception only from the state (objects are seen
# through the camera), as DP / DP3; DP3 predicts the clean sample and farthest-point samples its points, as its
# release.
OBS_CHANGES: dict[str, dict[str, Any]] = {
    "state": {},
    "image": {"encoder.obs_type": "image", "encoder.state_dims": PROPRIO_DIM},
    "pointcloud": {"encoder.obs_type": "pointcloud", "encoder.state_dims": PROPRIO_DIM,
                   "encoder.point_sampling": "fps", "diffusion.prediction_type": "sample"},
}
# Changes of an observation type on one budget. On the cpu budget DP3 sees 256 farthest-point-sampled points, the
# largest count whose DP3+HiPolicy run trains in <= 30 min on 2 cores (results/PROTOCOL.md: a train step at batch 64
# takes 1.38 s with 512 points, 1.00 s with 384, 0.71 s with 256; results/dp3_point_count_train_step.json).
# On Meta-World DP3 sees 512 points, as DP3 (results/metaworld/PROTOCOL.md).
BUDGET_OBS_CHANGES: dict[tuple[str, str], dict[str, Any]] = {("cpu", "pointcloud"): {"encoder.num_points": 256},
                                                             ("metaworld", "pointcloud"): {"encoder.num_points": 512}}

DP = (("chunk.strides", (1,)),)  # single frequency: Diffusion Policy


_ABBREV = {"chunk.obs_horizon": "lh", "chunk.chunk_len": "lc", "model.condition": "cond-", "objective": ""}


KIND_LETTERS = {"absolute": "a", "delta": "d"}


def kinds_name(kinds) -> str:
    """``chunk.action_kinds`` in a run-dir name: 'kinds-ddda' for (delta, delta, delta, absolute)."""
    return "kinds-" + "".join(KIND_LETTERS[k] for k in kinds)


def variant_name(changes: tuple[tuple[str, Any], ...]) -> str:
    """Canonical run-dir name of a set of config changes: 'hipolicy' (none), 'dp' (one stride), else e.g.
    'lh1', 'cond-low', 'nofusion', 's1-2', 'flow' (the flow-matching head); declared action kinds
    (``chunk.action_kinds``) follow the rest's name: 'dp_kinds-aaaa', 'hipolicy_kinds-ddda'."""
    kinds = [v for k, v in changes if k == "chunk.action_kinds"]
    if kinds:
        rest = tuple((k, v) for k, v in changes if k != "chunk.action_kinds")
        return f"{variant_name(rest)}_{kinds_name(kinds[0])}"
    changes = tuple(sorted(changes))
    if not changes:
        return "hipolicy"
    if changes == DP:
        return "dp"
    parts = []
    for key, value in changes:
        if key == "chunk.strides":
            parts.append("s" + "-".join(str(s) for s in value))
        elif key == "model.fusion":
            parts.append("fusion" if value else "nofusion")
        else:
            parts.append(_ABBREV.get(key, key.replace(".", "-") + "-") + str(value))
    return "_".join(parts)


# Run-level changes of a demo regime (keys: "episodes" = demos, "train.<field>"), per task. R100 is the budgets' own
# 100 demos; Rlow comes from results/PROTOCOL.md's DP pilot (python -m experiments.paper pilot) and is filled in
# here when the pilot has chosen it.
REGIMES: dict[str, dict[str, dict[str, Any]]] = {
    "r100": {},
    "rlow": {  # the DP pilot of 2026-12-01 (results/PROTOCOL.md): DP success at these demo counts
        "press_button": {"episodes": 25},  # 79 %
        "stack_cubes": {"episodes": 50},  # 26 %
        "latch_door": {"episodes": 12},  # 98 %: no candidate in [15, 85] %, the one closest to 50 % (rule 4)
        "pick_place": {"train.num_steps": 8000},  # 100 demos: 0 % at 2000 and 4000 steps, 5 % at 8000 (rule 4)
    },
}


def regime_changes(regime: str, task: str) -> dict[str, Any]:
    """The run-level changes of ``regime`` for ``task``; ValueError when the regime has no entry for the task."""
    if regime not in REGIMES:
        raise ValueError(f"regime: must be one of {sorted(REGIMES)}, got {regime!r}")
    if regime == "r100":
        return {}
    if task not in REGIMES[regime]:
        raise ValueError(f"regime {regime}: no entry for {task} yet in hipolicy_jax/campaigns/budgets.py REGIMES; run the "
                         f"DP pilot first (python -m experiments.paper pilot --tasks {task}) and record its choice")
    return dict(REGIMES[regime][task])


def run_changes_name(run_changes: dict[str, Any] | None) -> str:
    """Dir-name suffix of run-level changes: '' for none, e.g. '_d25' (25 demos), '_t4000' (4000 steps),
    '_t8000_speedup' (trained on the DemoSpeedup-accelerated demos, ``speedup_data_path``)."""
    parts = []
    for key, value in sorted((run_changes or {}).items()):
        if key == "speedup":
            if value is not True:
                raise ValueError(f"run_changes: 'speedup' is True (train on the accelerated demos) or absent, got "
                                 f"{value!r}")
            parts.append("speedup")
        elif key == "episodes":
            parts.append(f"d{value}")
        elif key == "train.num_steps":
            parts.append(f"t{value}")
        elif key.startswith("train."):
            parts.append(f"{key[6:].replace('_', '')}{value}")
        else:
            raise ValueError(f"run_changes: unknown key {key!r} (expected 'episodes', 'speedup' or 'train.<field>')")
    return "".join("_" + p for p in parts)


SPEEDUP_SUFFIX = "_speedup.zarr"


def speedup_data_path(data_path: str) -> str:
    """The DemoSpeedup-accelerated buffer made from the demo buffer at ``data_path``:
    ``<data>/<task>_state_100.zarr`` → ``<data>/<task>_state_100_speedup.zarr`` (``campaigns.speedup`` makes it
    from its proxy before any run trains on it)."""
    stem = data_path[:-len(".zarr")] if data_path.endswith(".zarr") else data_path
    return stem + SPEEDUP_SUFFIX


def run_dir(runs: str, budget: str, task: str, obs_type: str, changes, seed: int,
            run_changes: dict[str, Any] | None = None) -> str:
    """``<runs>/<budget>/<task>/<obs>/<variant><run changes>/seed<k>`` (an external task's ``suite:task`` as
    ``suite_task``)."""
    return os.path.join(runs, budget, task.replace(":", "_"), obs_type, variant_name(changes) + run_changes_name(run_changes),
                        f"seed{seed}")


def run_config(budget: str, task: str, obs_type: str, changes, seed: int, *, runs: str = "runs/paper",
               data: str = "data", eval_episodes: int | None = None, progress: bool = True,
               run_changes: dict[str, Any] | None = None) -> RunConfig:
    """The ``RunConfig`` of one run: the budget's configs + the observation type's + the variant's changes, the
    seed, its run dir under ``runs`` and its demo buffer under ``data``. ``run_changes`` (a regime's): the number of
    demos (``episodes``), training settings (``train.<field>``) and ``speedup`` (train on the DemoSpeedup-accelerated
    buffer of those demos, ``speedup_data_path``)."""
    b = BUDGETS[budget]
    run_changes = dict(run_changes or {})
    run_changes_name(run_changes)  # validates the keys
    policy = replace(b.policy, **{**OBS_CHANGES[obs_type], **BUDGET_OBS_CHANGES.get((budget, obs_type), {}),
                                  **dict(changes)})
    demos = int(run_changes.get("episodes", b.demos))
    train = replace(b.train, seed=seed, **{k[6:]: v for k, v in run_changes.items() if k.startswith("train.")})
    # every periodic checkpoint kept, with room for the first step's and an interrupted run's extra saves
    if b.checkpoints and "train.ckpt_every" not in run_changes:
        train = replace(train, ckpt_every=max(train.num_steps // b.checkpoints, 1), ckpt_keep=b.checkpoints + 2)
    elif "train.ckpt_every" in run_changes:  # a pilot reads every checkpoint at its interval
        train = replace(train, ckpt_keep=max(-(-train.num_steps // train.ckpt_every) + 2, train.ckpt_keep))
    if external.is_external(task):
        # one buffer (state and point clouds) serves every column: external.default_data_path
        data_path = os.path.join(data, os.path.basename(external.default_data_path(task, demos)))
    else:
        data_path = os.path.join(data, os.path.basename(default_data_path(task, policy.encoder, demos)))
    if run_changes.get("speedup"):
        data_path = speedup_data_path(data_path)
    episodes = b.eval.episodes if eval_episodes is None else eval_episodes
    return RunConfig(task=task, out=run_dir(runs, budget, task, obs_type, changes, seed, run_changes), data=data_path,
                     episodes=demos, val_ratio=b.val_ratio, policy=policy, train=train,
                     eval=dataclasses.replace(b.eval, episodes=episodes), inference=b.inference, progress=progress,
                     final_eval=False)
