"""The MJX task suite, the world at both ends of the flow: the source of the demonstrations (data) and the closed
loop of evaluation.

    **envs** (scripted experts -> demos, ``demos``) -> data -> encoders -> denoiser -> generative head -> sampling
    -> evaluation (rollouts in **envs**) -> experiments

* ``base``: ``MjxEnv`` (reset / step of ONE instance, MuJoCo Playground style; batch with ``jax.vmap``), ``State``
  and the scripted-expert plans (``ExpertPlan``);
* the tasks, one module each: ``press_button``, ``latch_door``, ``stack_cubes``, ``pick_place`` (MJCF in
  ``assets/``);
* ``camera``: the jitted ray-cast camera (RGB, depth, point cloud) the image and point-cloud observations come from;
* ``demos``: the scripted experts' demonstrations, collected in one jitted rollout and cached as a zarr
  ``ReplayBuffer`` (``collect_demos``, ``load_or_collect``);
* ``external``: tasks of other simulators (``metaworld:<task>``): no MJX env, demos from a bridge in its own venv;
* ``check_experts``: a command line: expert success, compile times and env throughput per task.

Public names here: ``make(task_name, **overrides) -> MjxEnv`` builds a task; ``TASKS`` lists the names and
``TASK_PRECISE`` the paper's precise / non-precise split; ``make_for_encoder`` / ``encoder_env_kwargs`` build a task
computing the observations a policy's encoder reads (with its camera); ``episode_limit`` is a task's step limit;
``check_task`` accepts MJX and external task names; ``MjxEnv``, ``State``, ``ExpertPlan`` and the ``external``
module. Rollouts and videos are the evaluation stage's (``hipolicy_jax.evaluation``). Within ``hipolicy_jax`` this
package imports only ``config`` and ``data``.
"""

from __future__ import annotations

from hipolicy_jax.config import EncoderConfig
from hipolicy_jax.envs.base import ExpertPlan, MjxEnv, State
from hipolicy_jax.envs import external
from hipolicy_jax.envs.camera import CameraConfig
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

# Which tasks need tight end-effector tolerances (the paper's precise / non-precise split); the one place it lives.
TASK_PRECISE: dict[str, bool] = {"press_button": True, "stack_cubes": True, "latch_door": False, "pick_place": False}


def check_task(task_name: str) -> None:
    """Raise ``ValueError`` unless ``task_name`` is an MJX task (``TASKS``) or an external one (``<suite>:<task>``,
    e.g. ``metaworld:assembly``)."""
    if task_name in _REGISTRY:
        return
    if ":" in task_name:
        external.check_name(task_name)
        return
    raise ValueError(f"task: must be one of {list(TASKS)} or an external task "
                     f"({' / '.join(f'{s}:<task>' for s in external.SUITES)}), got {task_name!r}")


def make(task_name: str, **overrides) -> MjxEnv:
    """Build the task ``task_name`` (one of ``TASKS``); ``overrides`` go to its constructor (control_dt, max_steps,
    obs_keys, camera, task-specific options)."""
    if external.is_external(task_name):
        raise ValueError(f"task_name: {task_name} is an external task with no MJX env: it cannot be rolled out "
                         f"in-process (evaluate it in its own simulator through the policy server)")
    if task_name not in _REGISTRY:
        raise ValueError(f"task_name: must be one of {TASKS}, got {task_name!r}")
    return _REGISTRY[task_name](**overrides)


def episode_limit(task_name: str) -> int:
    """The task's default episode step limit (``max_steps``; an external task's: its suite's campaign limit)."""
    if external.is_external(task_name):
        external.check_name(task_name)
        return external.SUITES[task_name.partition(":")[0]].eval_max_steps
    if task_name not in _REGISTRY:
        raise ValueError(f"task_name: must be one of {TASKS}, got {task_name!r}")
    return _REGISTRY[task_name].default_max_steps


def encoder_env_kwargs(encoder: EncoderConfig) -> dict:
    """``make`` / ``collect_demos`` keywords for a policy with this encoder: the ``obs_keys`` it reads and, for
    vision, the ``camera`` (``camera.CameraConfig``): images of ``image_size`` pixels square, or ``num_points`` points
    (with rgb when ``point_dims == 6``, down-sampled by ``point_sampling``) cast from the default camera
    resolution."""
    kwargs: dict = {"obs_keys": encoder.obs_keys}
    if encoder.obs_type == "image":
        kwargs["camera"] = CameraConfig(height=encoder.image_size, width=encoder.image_size)
    elif encoder.obs_type == "pointcloud":
        kwargs["camera"] = CameraConfig(num_points=encoder.num_points, point_rgb=encoder.point_dims == 6,
                                        sampling=encoder.point_sampling)
    return kwargs


def make_for_encoder(task_name: str, encoder: EncoderConfig = EncoderConfig(), **overrides) -> MjxEnv:
    """``make`` with the observations (and camera) a policy with ``encoder`` reads (``encoder_env_kwargs``)."""
    return make(task_name, **{**encoder_env_kwargs(encoder), **overrides})


__all__ = ["TASKS", "TASK_PRECISE", "check_task", "external", "make", "make_for_encoder", "encoder_env_kwargs",
           "episode_limit", "MjxEnv", "State", "ExpertPlan"]
