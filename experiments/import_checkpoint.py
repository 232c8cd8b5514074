"""Run a PyTorch policy's weights in JAX: ``python -m experiments.import_checkpoint {dp,hipolicy-release} CKPT OUT_RUN``.

Reads a Diffusion Policy workspace checkpoint (``DiffusionUnetLowdimPolicy`` or ``DiffusionUnetImagePolicy`` with
the ResNet-18 GroupNorm encoder) or a HiPolicy release checkpoint — weights, EMA weights, normaliser, noise
scheduler, observation and action shapes — and writes a run directory that ``experiments.evaluate``, ``calibrate``,
``export`` and ``serve`` use unchanged::

    python -m experiments.import_checkpoint dp data/outputs/.../checkpoints/latest.ckpt runs/dp_import \\
        --task press_button
    python -m experiments.evaluate --checkpoint runs/dp_import --episodes 50

``CKPT`` is a ``.ckpt`` (no torch needed: it is read with an allow-list unpickler that never runs code from the
file) or a ``.safetensors`` state dict with ``--config`` (the run's ``.hydra/config.yaml``, or a YAML / JSON with the
same keys). ``--task`` is the task the run evaluates on (its observation and action sizes must match the policy's);
``--data`` a demo buffer for ``calibrate``'s held-out windows. ``--weights model`` takes the training weights instead
of the EMA ones. The source's sampler (DDPM / DDIM and its step count) goes to the run's ``inference.json``;
``--inference.*`` flags of ``evaluate`` override it as for any run.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import tyro

from hipolicy_jax.porting.convert import convert, write_run


@dataclasses.dataclass(frozen=True)
class ImportArgs:
    kind: tyro.conf.Positional[Literal["dp", "hipolicy-release"]]  # whose checkpoint
    ckpt: tyro.conf.Positional[str]  # .ckpt, or .safetensors with --config
    out: tyro.conf.Positional[str]  # the run directory to write
    task: str = "press_button"  # the task the run evaluates on
    config: str | None = None  # workspace config (YAML / JSON); needed for safetensors, overrides a .ckpt's
    weights: Literal["ema", "model"] = "ema"  # EMA weights (Diffusion Policy evaluates them) or training weights
    data: str | None = None  # a demo buffer (zarr) for calibrate's held-out windows
    val_ratio: float = 0.1  # the held-out share of --data's episodes


def main(args: ImportArgs) -> str:
    from hipolicy_jax.envs import make

    conv = convert(args.kind, args.ckpt, args.config, args.weights)
    if ":" not in args.task:  # an MJX task: its sizes must be the policy's
        env = make(args.task)
        reads = conv.cfg.encoder.state_dims  # an image policy reads the first state_dims features; else all
        want = reads or conv.obs_shapes["state"][0]
        fits = env.state_dim >= want if reads else env.state_dim == want
        if env.action_dim != conv.action_dim or not fits:
            raise ValueError(f"task: {args.task} has actions of {env.action_dim} and states of {env.state_dim}; the "
                             f"checkpoint's policy takes actions of {conv.action_dim} and states of "
                             f"{'at least ' if reads else ''}{want}")
    run = write_run(conv, args.out, args.task, data=args.data, val_ratio=args.val_ratio)
    c = conv.cfg
    print(f"imported {conv.source['policy_target'] or args.kind} ({conv.source['weights']} weights, step "
          f"{conv.source['global_step']}) -> {run}: strides {list(c.chunk.strides)}, {c.chunk.obs_horizon} observed "
          f"frames, chunk {c.chunk.chunk_len} from offset {c.chunk.action_offset} ({c.chunk.exec_steps} executed), "
          f"U-Net {list(c.model.unet_dims)}, {conv.inference.sampler} x {conv.inference.num_steps}, task "
          f"{args.task}")
    return run


if __name__ == "__main__":
    try:
        main(tyro.cli(ImportArgs, description=__doc__))
    except (ValueError, FileNotFoundError, FileExistsError) as e:
        raise SystemExit(f"error: {e}")
