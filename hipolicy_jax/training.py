"""Training state, optimiser, EMA and the jitted train step of any generative head.

Diffusion Policy defaults: AdamW (lr 1e-4, betas 0.95/0.999, wd 1e-6) under a cosine schedule with linear warm-up,
EMA of the parameters with Diffusion Policy's decay: 0 at updates 1 and 2, then 1 − (k − 1)^−0.75 at update k,
clipped to 0.9999 (``ema_decay``). The loss is the generative head's (``heads``): MSE on ε or x0 at uniform DDPM
timesteps (diffusion), on the velocity ε − a (flow matching).

Keys: the step's key is ``fold_in(base_key, step)`` so a resumed run draws exactly the same noise as an
uninterrupted one.
"""

from __future__ import annotations

from typing import Any, Callable

import flax.struct
import jax
import jax.numpy as jnp
import optax

from hipolicy_jax.config import PolicyConfig, TrainConfig
from hipolicy_jax.heads import GenerativeHead, make_head


@flax.struct.dataclass
class TrainState:
    step: jax.Array  # int32 scalar: number of updates applied
    params: Any
    ema_params: Any
    opt_state: Any


def lr_schedule(cfg: TrainConfig) -> optax.Schedule:
    """Learning rate of the update after ``count`` updates: linear warm-up from 0 to ``lr`` over ``warmup_steps``,
    then cosine decay to 0 at ``num_steps``; diffusers' ``get_cosine_schedule_with_warmup`` (Diffusion Policy's
    ``get_scheduler('cosine')``), whose update k uses its factor at k - 1 as here. A run no longer than its warm-up
    only warms up (``lr * count / warmup_steps``), as there."""
    if cfg.warmup_steps >= cfg.num_steps:
        return optax.linear_schedule(0.0, cfg.lr, cfg.warmup_steps)
    return optax.warmup_cosine_decay_schedule(0.0, cfg.lr, cfg.warmup_steps, cfg.num_steps, end_value=0.0)


def make_optimizer(cfg: TrainConfig) -> optax.GradientTransformation:
    adamw = optax.adamw(lr_schedule(cfg), b1=cfg.betas[0], b2=cfg.betas[1], weight_decay=cfg.weight_decay)
    if cfg.grad_clip is None:
        return adamw
    return optax.chain(optax.clip_by_global_norm(cfg.grad_clip), adamw)


def ema_decay(step: jax.Array, cfg: TrainConfig) -> jax.Array:
    """Diffusion Policy's EMA warm-up: 0 for the first update, then 1 − (1 + s)^−power, s = step − 1, clipped to
    ``ema_max_decay``: DP's ``EMAModel.get_decay(step)``. The train step applies ``ema_decay(k - 1)`` at update k,
    as DP's workspace does (``EMAModel.step`` reads its count before counting the update): decays 0, 0, 0.405,
    0.561, ... for updates 1, 2, 3, 4."""
    s = jnp.asarray(step, jnp.float32) - 1.0
    decay = 1.0 - (1.0 + s) ** (-cfg.ema_power)
    return jnp.where(s <= 0, 0.0, jnp.clip(decay, 0.0, cfg.ema_max_decay))


def init_train_state(params, tx: optax.GradientTransformation) -> TrainState:
    # The EMA copy must not alias ``params``: the train step donates the whole state.
    ema = jax.tree.map(jnp.copy, params)
    return TrainState(step=jnp.zeros((), jnp.int32), params=params, ema_params=ema, opt_state=tx.init(params))


def policy_loss(params, batch: dict, key: jax.Array, *, net, head: GenerativeHead) -> jax.Array:
    """The generative head's regression loss (MSE). batch: {"obs": {k: (B, M, L_h, ...)}, "action": (B, M·L_c, A)}
    normalised."""
    k_crop, k_head = jax.random.split(key)
    cond = net.apply(params, batch["obs"], train=True, method=net.encode, rngs={"crop": k_crop})
    example = head.training_example(batch["action"], k_head)
    pred = net.apply(params, example.x, example.time, cond, method=net.denoise)
    return jnp.mean(jnp.square(pred - example.target))


def apply_gradients(state: TrainState, grads, tx: optax.GradientTransformation, train_cfg: TrainConfig) -> TrainState:
    """One update of ``state`` by ``grads``: ``tx`` (AdamW under the schedule), then the EMA (``ema_decay``)."""
    updates, opt_state = tx.update(grads, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    if train_cfg.ema:
        ema = optax.incremental_update(params, state.ema_params, 1.0 - ema_decay(state.step, train_cfg))
    else:
        ema = params
    return TrainState(step=state.step + 1, params=params, ema_params=ema, opt_state=opt_state)


def make_train_step(net, cfg: PolicyConfig, train_cfg: TrainConfig,
                    tx: optax.GradientTransformation) -> Callable[[TrainState, dict, jax.Array], tuple]:
    """Jitted ``step(state, batch, base_key) -> (state, metrics)``; ``state`` is donated.

    metrics: loss, grad_norm, lr, finite (False if the loss or gradients went NaN/Inf; the update is then skipped
    so the last good state survives for the caller to report).
    """
    schedule = lr_schedule(train_cfg)
    head = make_head(cfg)

    def step(state: TrainState, batch: dict, base_key: jax.Array):
        key = jax.random.fold_in(base_key, state.step)
        loss, grads = jax.value_and_grad(policy_loss)(state.params, batch, key, net=net, head=head)
        grad_norm = optax.tree.norm(grads)
        finite = jnp.isfinite(loss) & jnp.isfinite(grad_norm)

        # A branch, not a select over the whole state: the optimizer and EMA fuse into one in-place pass over the
        # donated buffers (a tree-wide ``where`` read old and new state again and took 3/4 of the update's time).
        new = jax.lax.cond(finite, lambda s: apply_gradients(s, grads, tx, train_cfg), lambda s: s, state)
        metrics = {"loss": loss, "grad_norm": grad_norm, "lr": schedule(state.step), "finite": finite}
        return new, metrics

    return jax.jit(step, donate_argnums=0)
