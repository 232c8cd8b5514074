"""MJX task suite for hipolicy_jax: registry of tasks.

``make(task_name, **overrides) -> MjxEnv`` builds a task; ``TASKS`` lists the names. See ``base.py`` for the API.
"""

from __future__ import annotations

from hipolicy_jax.envs.base import ExpertPlan, MjxEnv, State
from hipolicy_jax.envs.latch_door import LatchDoor
from hipolicy_jax.envs.pick_place import PickPlace
from hipolicy_jax.envs.press_button import PressButton
from hipolicy_jax.envs.stack_cubes import StackCubes

_REGISTRY: dict[str, type[MjxEnv]] = {
    "press_button": PressButton,
    "latch_door": LatchDoor,
    "stack_cubes": StackCubes,
    "pick_place": PickPlace,
}

TASKS: tuple[str, ...] = tuple(_REGISTRY)


def make(task_name: str, **overrides) -> MjxEnv:
    """Build the task ``task_name`` (one of ``TASKS``); ``overrides`` go to its constructor (control_dt, max_steps,
    obs_keys, camera, task-specific options)."""
    if task_name not in _REGISTRY:
        raise ValueError(f"task_name: must be one of {TASKS}, got {task_name!r}")
    return _REGISTRY[task_name](**overrides)


__all__ = ["TASKS", "make", "MjxEnv", "State", "ExpertPlan"]
