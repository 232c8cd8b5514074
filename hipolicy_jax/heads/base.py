"""The generative-head interface: what a head gives training and what the one sampler scans.

A head turns the denoiser network into a generative model of action chunks. It owns two things and nothing else:

- **training**: ``training_example(x0, key) -> TrainingExample(x, time, target)``: the network input built from the
  clean normalised chunk ``x0`` ``(B, T, A)``, the time input ``(B,)`` the network is conditioned on, and the
  regression target; the loss is the mean squared error between the network's output and ``target``.
- **sampling**: ``plan(inference) -> StepPlan``: a precomputed table of per-step arrays (each ``(S,)``, applied in
  order, ``table.time`` the network's time input at that step) and ``update(row, x, model_out, key) -> x_next``, the
  rule applied at every step; ``finish(x)`` runs once after the last step; ``renoise(row, x0, noise)`` is where
  a chain whose clean sample is ``x0`` stands after that step (the path's marginal at the step's target level:
  ``x0`` itself after the last step), which prefix inpainting writes into the known actions after each update.
  ``sampling.denoise_chain`` scans the table; the N-sample entropy, stride selection and evaluation are the same
  code path for every head.

Heads are frozen dataclasses (hashable, usable as static arguments of ``jax.jit``) built from a ``PolicyConfig`` by
the registry in ``heads/__init__.py``. Adding a head = one module here + one registry line.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple, Protocol

import jax

from hipolicy_jax.config import InferenceConfig


class TrainingExample(NamedTuple):
    """One training example of a head: network input ``x`` (B, T, A), time input ``time`` (B,), ``target``
    (B, T, A) the network regresses."""

    x: jax.Array
    time: jax.Array
    target: jax.Array


class StepPlan(NamedTuple):
    """What the sampler scans: ``table`` (a NamedTuple of (S,) arrays with a ``time`` field), the per-step
    ``update(row, x, model_out, key) -> x_next``, ``finish(x) -> x`` after the last step and
    ``renoise(row, x0, noise) -> x_next`` the marginal of a chain with clean sample ``x0`` after the step."""

    table: Any
    update: Callable[[Any, jax.Array, jax.Array, jax.Array], jax.Array]
    finish: Callable[[jax.Array], jax.Array]
    renoise: Callable[[Any, jax.Array, jax.Array], jax.Array]


class GenerativeHead(Protocol):
    name: str

    def training_example(self, x0: jax.Array, key: jax.Array) -> TrainingExample: ...

    def plan(self, inference: InferenceConfig) -> StepPlan: ...

    def describe(self, inference: InferenceConfig) -> str: ...


def identity(x: jax.Array) -> jax.Array:
    return x
