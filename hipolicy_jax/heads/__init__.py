"""Generative heads, the stage between the denoiser and sampling: what the network's output means.

    encoders -> denoiser (``models``) -> **generative head** -> sampling (``hipolicy_jax.sampling``) / training
    (``hipolicy_jax.training``)

A head owns the training objective (``training_example``: the network input, time input and regression target of
a clean chunk) and the sampling rule (``plan``: a per-step table and the update the one sampler scans); the network,
the entropy and the stride selection are the same for every head.

* ``base``: the interface, ``GenerativeHead`` (a protocol), ``TrainingExample`` and ``StepPlan``;
* ``diffusion``: ``DiffusionHead``, DDPM training and DDPM / DDIM / clipped-DDIM sampling over one reverse-step table;
* ``flow``: ``FlowHead``, conditional flow matching on the linear path and Euler sampling.

``PolicyConfig.objective`` names the head; ``make_head(cfg)`` builds it from ``HEADS``. Public names here:
``HEADS``, ``make_head``, ``GenerativeHead``, ``StepPlan``, ``TrainingExample``. Adding a head = one module in this
package (a frozen dataclass with ``name``, ``training_example``, ``plan`` and ``describe``, and a ``make(cfg)``)
+ one line in ``HEADS``. Within ``hipolicy_jax`` this package imports only ``config``.
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
