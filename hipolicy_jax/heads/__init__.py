"""Generative heads: the training objective and the sampling update of a policy (``base`` has the interface).

``PolicyConfig.objective`` names the head; ``make_head(cfg)`` builds it. Adding a head = one module in this package
(a frozen dataclass with ``training_example``, ``plan`` and ``describe``, and a ``make(cfg)``) + one line here.
"""

from __future__ import annotations

from typing import Callable

from hipolicy_jax.config import PolicyConfig
from hipolicy_jax.heads import diffusion, flow
from hipolicy_jax.heads.base import GenerativeHead, StepPlan, TrainingExample

HEADS: dict[str, Callable[[PolicyConfig], GenerativeHead]] = {
    "diffusion": diffusion.make,
    "flow": flow.make,
}


def make_head(cfg: PolicyConfig) -> GenerativeHead:
    """The generative head of ``cfg.objective``."""
    if cfg.objective not in HEADS:
        raise ValueError(f"policy.objective: must be one of {sorted(HEADS)}, got {cfg.objective!r}")
    return HEADS[cfg.objective](cfg)


__all__ = ["HEADS", "GenerativeHead", "StepPlan", "TrainingExample", "make_head"]
