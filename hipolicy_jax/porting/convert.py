"""A PyTorch policy checkpoint -> our policy: config, parameters, normaliser, inference settings; and a run directory.

Sources (``kind``):

* ``dp``: a Diffusion Policy workspace checkpoint of ``DiffusionUnetLowdimPolicy`` (state, ``obs_as_global_cond``)
  or ``DiffusionUnetImagePolicy`` (one rgb camera through ``MultiImageObsEncoder``'s ResNet-18 with GroupNorm, and
  at most one low-dim key). One stride; the chunk is Diffusion Policy's ``horizon`` steps from the first observed
  frame (``chunk.action_offset = -(n_obs_steps - 1)``), of which ``n_action_steps`` from the current frame run
  (``chunk.exec_len``).
* ``hipolicy-release``: a HiPolicy release checkpoint (its ``DiffusionUnetImagePolicy``: the same image encoder, the
  hierarchical U-Net with the release's fusion, ``model.fusion_kind='release'``). Strides 1 / ``mid_interval`` /
  ``long_interval`` with 3 observed frames each and 8 actions from the frame after the current one.

The input is a ``.ckpt`` (``torch_checkpoint.read_torch_file``: its config and state dicts, no torch needed) or a
``safetensors`` state dict with the workspace config beside it (``--config``: the run's ``.hydra/config.yaml`` or
any YAML / JSON of the same keys). The EMA weights are used when the checkpoint has them (``state_dicts.ema_model``),
as Diffusion Policy evaluates; ``weights='model'`` takes the training weights.

Observation keys become ours: the low-dim key -> ``state``, the camera -> ``image`` (uint8 ``(H, W, 3)``, which our
``image_to_float`` maps to [-1, 1] as Diffusion Policy's range normaliser does for its [0, 1] images).
"""

from __future__ import annotations

import dataclasses
import json
import os
from typing import Any, Literal

import jax
import jax.numpy as jnp
import numpy as np

from hipolicy_jax.config import (ChunkConfig, DiffusionConfig, EncoderConfig, InferenceConfig, ModelConfig,
                                 PolicyConfig, TrainConfig)
from hipolicy_jax.data.normalizer import Normalizer
from hipolicy_jax.porting.encoders import RESNET18_CHANNELS, resnet_params_from_torch
from hipolicy_jax.porting.torch_checkpoint import (plain_config, read_safetensors, read_torch_file,
                                                   resolve_config)
from hipolicy_jax.porting.unet import unet_params, unet_shape

SourceKind = Literal["dp", "hipolicy-release"]
LOWDIM_POLICIES = ("diffusion_policy.policy.diffusion_unet_lowdim_policy.DiffusionUnetLowdimPolicy",)
IMAGE_POLICIES = ("diffusion_policy.policy.diffusion_unet_image_policy.DiffusionUnetImagePolicy",)


@dataclasses.dataclass(frozen=True)
class Converted:
    """What a converted checkpoint holds: ``cfg``, ``action_dim``, ``obs_shapes`` (per-frame, ours: ``state`` ``(D,)``,
    ``image`` ``(H, W, 3)``), ``variables`` ``{"params": ...}`` for ``PolicyNet`` (the weights evaluated),
    ``train_variables`` (the training weights, when the checkpoint has both), ``normalizer``, ``inference`` (the
    sampler the source's config runs) and ``source`` (where it came from, for the run's meta)."""

    cfg: PolicyConfig
    action_dim: int
    obs_shapes: dict[str, tuple[int, ...]]
    variables: dict
    train_variables: dict
    normalizer: Normalizer
    inference: InferenceConfig
    source: dict


def load_source(path: str, config: str | None = None) -> tuple[dict, dict[str, dict[str, np.ndarray]], int]:
    """``(workspace config, {"model": state dict[, "ema_model": ...]}, global step)`` from a ``.ckpt`` or a
    ``safetensors`` file (+ ``config``, a YAML / JSON file: needed for safetensors, overrides a ``.ckpt``'s)."""
    step = 0
    if path.endswith(".safetensors"):
        if config is None:
            raise ValueError(f"--config: a safetensors file holds weights only; pass the workspace config (the "
                             f"run's .hydra/config.yaml, or a YAML / JSON with horizon, n_obs_steps, n_action_steps, "
                             f"policy) for {path}")
        states = {"model": read_safetensors(path)}
        cfg: dict = {}
    else:
        payload = read_torch_file(path)
        if not isinstance(payload, dict) or "state_dicts" not in payload:
            raise ValueError(f"checkpoint: {path} is not a Diffusion Policy workspace checkpoint (a dict with "
                             f"'cfg' and 'state_dicts'); for a bare state dict save it as safetensors and pass "
                             f"--config")
        cfg = plain_config(payload.get("cfg")) or {}
        states = {k: v for k, v in payload["state_dicts"].items() if k in ("model", "ema_model")}
        step = _pickled_int(payload.get("pickles", {}).get("global_step"))
    if config is not None:
        cfg = _read_config(config)
    if not cfg:
        raise ValueError(f"checkpoint: {path} carries no workspace config; pass --config")
    return resolve_config(cfg), states, step


def _pickled_int(blob) -> int:
    """A workspace's ``global_step`` (a pickled int); 0 when absent or anything but a plain int."""
    import pickle
    import pickletools

    if not isinstance(blob, bytes):
        return 0
    if any(op.name in ("GLOBAL", "STACK_GLOBAL", "REDUCE", "INST", "OBJ", "NEWOBJ") for op, _, _ in
           pickletools.genops(blob)):
        return 0
    value = pickle.loads(blob)  # opcodes checked above: literals only
    return int(value) if isinstance(value, int) else 0


def _read_config(path: str) -> dict:
    if not os.path.isfile(path):
        raise FileNotFoundError(f"--config: {path} does not exist")
    with open(path) as f:
        text = f.read()
    if path.endswith(".json"):
        return json.loads(text)
    import yaml

    return yaml.safe_load(text)


def _get(cfg: dict, path: str, default: Any = KeyError) -> Any:
    node: Any = cfg
    for part in path.split("."):
        if not isinstance(node, dict) or part not in node:
            if default is KeyError:
                raise ValueError(f"config: the workspace config has no {path!r}")
            return default
        node = node[part]
    return node


def diffusion_settings(cfg: dict) -> tuple[DiffusionConfig, InferenceConfig]:
    """Our ``DiffusionConfig`` and sampler from the workspace's ``policy.noise_scheduler`` and
    ``policy.num_inference_steps``; a setting we do not implement raises ``ValueError`` naming it."""
    ns = _get(cfg, "policy.noise_scheduler")
    target = str(ns.get("_target_", ""))
    sampler = {"diffusers.schedulers.scheduling_ddpm.DDPMScheduler": "ddpm",
               "diffusers.schedulers.scheduling_ddim.DDIMScheduler": "ddim"}.get(target)
    if sampler is None:
        raise ValueError(f"config: policy.noise_scheduler._target_ {target!r} is not a diffusers DDPMScheduler or "
                         f"DDIMScheduler")
    if sampler == "ddpm" and ns.get("variance_type", "fixed_small") != "fixed_small":
        raise ValueError(f"config: policy.noise_scheduler.variance_type {ns['variance_type']!r}: only "
                         f"'fixed_small' (Diffusion Policy's) is implemented")
    if sampler == "ddim" and (not ns.get("set_alpha_to_one", True) or ns.get("steps_offset", 0) != 0):
        raise ValueError("config: policy.noise_scheduler: DDIM with set_alpha_to_one=False or steps_offset != 0 "
                         "is not implemented")
    if ns.get("thresholding", False):
        raise ValueError("config: policy.noise_scheduler.thresholding is not implemented")
    diff = DiffusionConfig(num_train_steps=int(ns.get("num_train_timesteps", 1000)),
                           beta_schedule=ns.get("beta_schedule", "linear"),
                           beta_start=float(ns.get("beta_start", 1e-4)), beta_end=float(ns.get("beta_end", 0.02)),
                           prediction_type=ns.get("prediction_type", "epsilon"),
                           clip_sample=bool(ns.get("clip_sample", True)),
                           clip_range=float(ns.get("clip_sample_range", 1.0)))
    steps = _get(cfg, "policy.num_inference_steps", None)
    steps = diff.num_train_steps if steps in (None, "None") else int(steps)
    return diff, InferenceConfig(num_samples=1, sampler=sampler, num_steps=steps)


def _normalizer(sd: dict[str, np.ndarray], keys: dict[str, str]) -> Normalizer:
    """Our normaliser from ``normalizer.params_dict.<theirs>.{scale, offset, input_stats.min, input_stats.max}``;
    ``keys`` maps their key -> ours."""
    stats = {}
    for theirs, ours in keys.items():
        base = f"normalizer.params_dict.{theirs}."
        missing = [n for n in ("scale", "offset", "input_stats.min", "input_stats.max") if base + n not in sd]
        if missing:
            raise ValueError(f"normalizer: the state dict lacks {[base + n for n in missing]}")
        stats[ours] = {"scale": sd[base + "scale"], "offset": sd[base + "offset"],
                       "min": sd[base + "input_stats.min"], "max": sd[base + "input_stats.max"]}
    return Normalizer.from_dict(stats)


def _obs_keys(cfg: dict, n_low_max: int = 1) -> tuple[str | None, str | None, tuple[int, ...] | None, int | None]:
    """(rgb key, low-dim key, rgb shape (C, H, W), low-dim size) from the workspace's ``shape_meta``."""
    obs = _get(cfg, "shape_meta.obs", None) or _get(cfg, "task.shape_meta.obs")
    rgb = [k for k, v in obs.items() if v.get("type", "low_dim") == "rgb"]
    low = [k for k, v in obs.items() if v.get("type", "low_dim") == "low_dim"]
    if len(rgb) != 1 or len(low) > n_low_max:
        raise ValueError(f"config: shape_meta.obs has rgb keys {rgb} and low-dim keys {low}; one camera and at most "
                         f"{n_low_max} low-dim key are supported (ours: 'image' and 'state')")
    shape = tuple(int(s) for s in obs[rgb[0]]["shape"])
    if len(shape) != 3 or shape[0] != 3 or shape[1] != shape[2]:
        raise ValueError(f"config: shape_meta.obs.{rgb[0]}.shape must be (3, H, H), got {shape}")
    return rgb[0], (low[0] if low else None), shape, (int(np.prod(obs[low[0]]["shape"])) if low else None)


def _image_encoder(cfg: dict, sd: dict[str, np.ndarray], rgb: str, size: int) -> tuple[dict, int]:
    """(encoder params, crop size) of ``MultiImageObsEncoder``'s ResNet-18 for the camera ``rgb``."""
    enc = _get(cfg, "policy.obs_encoder")
    name = _get(cfg, "policy.obs_encoder.rgb_model.name", "resnet18")
    if name != "resnet18" or not enc.get("use_group_norm", False) or not enc.get("imagenet_norm", False):
        raise ValueError(f"config: policy.obs_encoder must be a resnet18 with use_group_norm and imagenet_norm (the "
                         f"release's and Diffusion Policy's real-robot encoder), got rgb_model {name!r}, "
                         f"use_group_norm={enc.get('use_group_norm')}, imagenet_norm={enc.get('imagenet_norm')}")
    if enc.get("resize_shape") not in (None, "None"):
        raise ValueError(f"config: policy.obs_encoder.resize_shape {enc['resize_shape']} is not implemented; "
                         f"resize the images before they reach the policy")
    crop = enc.get("crop_shape")
    crop_size = size if crop in (None, "None") else int(crop[0])
    if crop not in (None, "None") and (crop[0] != crop[1] or not enc.get("random_crop", True)):
        raise ValueError(f"config: policy.obs_encoder.crop_shape {crop} with random_crop="
                         f"{enc.get('random_crop')}: a square random crop (or none) is supported")
    prefix = "obs_encoder.shared_model." if enc.get("share_rgb_model", False) else f"obs_encoder.key_model_map.{rgb}."
    return resnet_params_from_torch(sd, prefix=prefix), crop_size


def _variables(cfg: PolicyConfig, action_dim: int, obs_shapes: dict, unet: dict, encoder: dict | None) -> dict:
    """``{"params": ...}`` in ``PolicyNet``'s tree, checked against its own initialisation (names and shapes)."""
    from hipolicy_jax.models.policy_net import init_policy_params

    example = {k: np.zeros((1, cfg.chunk.num_freqs, cfg.chunk.obs_horizon, *s), np.float32)
               for k, s in obs_shapes.items()}
    abstract = jax.eval_shape(lambda: init_policy_params(cfg, action_dim, example, jax.random.key(0)))["params"]
    params = {"unet": unet}
    if encoder is not None:
        params["obs_encoder"] = {"image": encoder}
    want = {jax.tree_util.keystr(p): tuple(x.shape) for p, x in jax.tree_util.tree_leaves_with_path(abstract)}
    got = {jax.tree_util.keystr(p): tuple(np.shape(x)) for p, x in jax.tree_util.tree_leaves_with_path(params)}
    if want != got:
        diff = sorted(set(want.items()) ^ set(got.items()))[:4]
        raise ValueError(f"convert: the mapped parameters do not match the network the config builds: {diff}")
    return {"params": jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), params)}


def convert(kind: SourceKind, path: str, config: str | None = None,
            weights: Literal["ema", "model"] = "ema") -> Converted:
    """Convert the checkpoint at ``path`` (see the module docstring); raises ``ValueError`` naming what does not
    fit."""
    if kind not in ("dp", "hipolicy-release"):
        raise ValueError(f"kind: must be 'dp' or 'hipolicy-release', got {kind!r}")
    cfg, states, step = load_source(path, config)
    use = "ema_model" if weights == "ema" and "ema_model" in states else "model"
    sd = states[use]
    diff, inference = diffusion_settings(cfg)
    target = str(_get(cfg, "policy._target_", ""))
    shape = unet_shape(sd, "model.")
    if kind == "dp":
        if shape["hierarchical"]:
            raise ValueError(f"checkpoint: {path} has the release's fusion modules; convert it as hipolicy-release")
        if not _get(cfg, "policy.obs_as_global_cond", True) or shape["local_cond"]:
            raise ValueError("config: policy.obs_as_global_cond must be True (the observation as FiLM condition)")
        if not _get(cfg, "policy.oa_step_convention", True):
            raise ValueError("config: policy.oa_step_convention=False is not supported (actions aligned one step "
                             "later than Diffusion Policy's default)")
        n_obs, horizon = int(_get(cfg, "n_obs_steps")), int(_get(cfg, "horizon"))
        n_act = int(_get(cfg, "policy.n_action_steps", _get(cfg, "n_action_steps")))
        chunk = ChunkConfig(strides=(1,), obs_horizon=n_obs, chunk_len=horizon, action_offset=-(n_obs - 1),
                            exec_len=n_act)
    else:
        mid, long_ = int(_get(cfg, "policy.mid_interval", 2)), int(_get(cfg, "policy.long_interval", 3))
        chunk = ChunkConfig(strides=(1, mid, long_), obs_horizon=3, chunk_len=8, action_offset=1)
        if not shape["hierarchical"]:
            raise ValueError(f"checkpoint: {path} has no fusion modules (down_modules.0.0.global_feature_extractor); "
                             f"convert it as dp")
    action_dim = shape["action_dim"]
    model = ModelConfig(down_dims=shape["down_dims"], kernel_size=shape["kernel_size"],
                        step_embed_dim=shape["step_embed_dim"], n_groups=int(_get(cfg, "policy.model.n_groups",
                                                                                _get(cfg, "policy.n_groups", 8))),
                        fusion_kind="release")
    unet = unet_params(sd, "model.", chunk_len=chunk.chunk_len, fusion_kind="release")
    per_frame = shape["cond_dim"] // chunk.obs_horizon
    if target in LOWDIM_POLICIES:
        obs_dim = per_frame
        encoder_cfg, encoder, obs_shapes = EncoderConfig(obs_type="state", state_encoder="identity"), None, \
            {"state": (obs_dim,)}
        norm = _normalizer(sd, {"obs": "state", "action": "action"})
    elif target in IMAGE_POLICIES or kind == "hipolicy-release":
        rgb, low, (_, size, _), low_dim = _obs_keys(cfg)
        encoder, crop = _image_encoder(cfg, sd, rgb, size)
        if per_frame != 512 + (low_dim or 0):
            raise ValueError(f"checkpoint: the U-Net's condition is {shape['cond_dim']} = {chunk.obs_horizon} frames "
                             f"x {per_frame}, but the encoder gives 512 + {low_dim or 0} per frame")
        encoder_cfg = EncoderConfig(obs_type="image", state_encoder="identity", image_encoder="resnet_avgpool",
                                    image_size=size, crop_size=crop, image_channels=RESNET18_CHANNELS,
                                    state_dims=low_dim)
        obs_shapes = {"state": (low_dim or 1,), "image": (size, size, 3)}
        if low is None:
            raise ValueError("config: shape_meta.obs needs one low-dim key (ours: 'state'); image-only policies are "
                             "not supported yet")
        norm = _normalizer(sd, {low: "state", "action": "action"})
    else:
        raise ValueError(f"config: policy._target_ {target!r} is not supported; supported: "
                         f"{list(LOWDIM_POLICIES + IMAGE_POLICIES)} (and the release's DiffusionUnetImagePolicy)")
    cfg_ours = PolicyConfig(chunk=chunk, encoder=encoder_cfg, model=model, objective="diffusion", diffusion=diff)
    variables = _variables(cfg_ours, action_dim, obs_shapes, unet, encoder)
    train_variables = variables
    if use == "ema_model" and "model" in states:
        enc_train = (_image_encoder(cfg, states["model"], _obs_keys(cfg)[0], obs_shapes["image"][0])[0]
                     if encoder is not None else None)
        train_variables = _variables(cfg_ours, action_dim, obs_shapes,
                                     unet_params(states["model"], "model.", chunk_len=chunk.chunk_len,
                                                 fusion_kind="release"), enc_train)
    source = {"kind": kind, "path": os.path.abspath(path), "weights": use, "policy_target": target,
              "global_step": step}
    return Converted(cfg_ours, action_dim, obs_shapes, variables, train_variables, norm, inference, source)


def write_run(conv: Converted, out: str, task: str, *, data: str | None = None, val_ratio: float = 0.1) -> str:
    """Write ``conv`` as a run directory: ``checkpoints/<step>/`` (the evaluated weights as EMA parameters, the
    training weights as parameters, a fresh optimiser state, the normaliser, meta naming the source) and
    ``inference.json`` (the source's sampler). ``data``: a demo buffer for ``calibrate`` (held-out windows). Refuses
    a directory that already holds checkpoints. Returns the run directory."""
    from hipolicy_jax.checkpoint import Checkpointer, config_to_dict
    from hipolicy_jax.envs import check_task
    from hipolicy_jax.runs.store import write_inference
    from hipolicy_jax.training import TrainState, make_optimizer

    check_task(task)
    ckpt_dir = os.path.join(out, "checkpoints")
    if os.path.isdir(ckpt_dir) and any(d.isdigit() for d in os.listdir(ckpt_dir)):
        raise FileExistsError(f"out: {out} already holds checkpoints; pick a new directory")
    os.makedirs(out, exist_ok=True)
    train = TrainConfig()
    tx = make_optimizer(train)
    state = TrainState(step=jnp.asarray(conv.source["global_step"], jnp.int32), params=conv.train_variables,
                       ema_params=conv.variables, opt_state=tx.init(conv.train_variables))
    meta = {"policy": config_to_dict(conv.cfg), "train": config_to_dict(train), "action_dim": conv.action_dim,
            "obs_shapes": {k: list(v) for k, v in conv.obs_shapes.items()}, "task": task,
            "imported_from": conv.source}
    if data is not None:
        meta.update(data=os.path.abspath(data), val_ratio=float(val_ratio))
    with Checkpointer(ckpt_dir, every=1, keep=1) as ckpt:
        ckpt.save(int(conv.source["global_step"]), state, conv.normalizer, meta, force=True)
    write_inference(out, conv.inference)
    return os.path.abspath(out)


__all__ = ["Converted", "convert", "diffusion_settings", "load_source", "write_run"]
