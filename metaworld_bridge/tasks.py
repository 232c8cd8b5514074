"""Meta-World task names and DP3's difficulty groups (3D Diffusion Policy, arXiv 2403.03954, Meta-World table;
groups from Seo et al., "Masked World Models for Visual Control")."""

from __future__ import annotations

DP3_GROUPS: dict[str, tuple[str, ...]] = {
    "medium": ("basketball", "bin-picking", "box-close", "coffee-pull", "coffee-push", "hammer", "peg-insert-side",
               "push-wall", "soccer", "sweep", "sweep-into"),
    "hard": ("assembly", "hand-insert", "pick-out-of-hole", "pick-place", "push", "push-back"),
    "very_hard": ("shelf-place", "disassemble", "stick-pull", "stick-push", "pick-place-wall"),
}


def env_name(task: str) -> str:
    """Meta-World's v3 env name of a task: ``assembly`` → ``assembly-v3`` (a name with ``-v3`` is kept)."""
    return task if task.endswith("-v3") else f"{task}-v3"


def task_name(name: str) -> str:
    """The bare task name: ``assembly-v3`` → ``assembly``."""
    return name[:-3] if name.endswith("-v3") else name
