"""Write the PyTorch reference fixtures of tests/fixtures/torch/ with the unmodified upstream code.

Two parts, each in its own process (both define a package named ``diffusion_policy``):

* ``dp``: Diffusion Policy (``real-stanford/diffusion_policy``, commit 5ba07ac). Its own Hydra config
  ``train_diffusion_unet_lowdim_workspace.yaml`` is composed with small overrides (state 7-D and action 4-D as our
  ``press_button`` task; ``down_dims [16, 32]``, step embedding 16; horizon 16, 2 observation steps, 8 executed),
  its ``TrainDiffusionUnetLowdimWorkspace`` builds the policy, EMA copy and AdamW, its ``LinearNormalizer`` is
  fitted on synthetic data (one state dimension constant, to exercise ``range_eps``), the EMA weights are moved
  away from the training weights (so a converter that reads the wrong copy fails), and the workspace's own
  ``save_checkpoint`` writes ``dp_lowdim.ckpt``: the file a user of Diffusion Policy has. ``dp_lowdim.npz`` holds
  what the EMA policy computes: the denoiser's output on fixed inputs (``x (B, 16, 4)``, timesteps, raw observations
  ``obs (B, 2, 7)`` normalised and flattened as ``predict_action`` does), one DDPM step of its noise scheduler with
  the noise it drew (at t = 99, 50, 1, 0), one step of diffusers' ``DDIMScheduler`` with 10 inference steps (as
  DP's DDIM configs; t = 90, 40, 0), and the normaliser's round trip. ``dp_lowdim_ema.safetensors`` is the EMA policy's state dict
  alone, the torch-free form ``experiments.import_checkpoint`` also reads. ``dp_image.npz`` /
  ``dp_image_config.yaml``: DP's own ``DiffusionUnetImagePolicy`` with its ResNet-18 encoder (``make_dp_image``).
* ``release``: the HiPolicy release (``HzmSailor/HiPolicy``, folder ``release/HiPolicy``): its
  ``conditional_unet1d.py`` and ``cross_attention.py`` laid over Diffusion Policy's package, as the release runs
  them, with ``HIPOLICY_BENCHMARK=robotwin_v2``. A hierarchical ``ConditionalUnet1D`` (action 4-D, L_c 8,
  ``down_dims [16, 32]``, kernel 5, step embedding 16, per-stride condition 21-D) is built with its random
  initialisation (``torch.manual_seed``); ``release_unet.npz`` holds its state dict (``sd/<name>``), fixed inputs
  and its output, the first fusion module's output for two different inputs and batch sizes (the release's learned
  constant) and, from the same ``nn.MultiheadAttention`` fed sequence-first (``(M+1, B, D)``, the attention over
  each sample's tokens the paper describes), the per-sample fusion output our ``fusion_kind='attention'`` computes.
  ``release_policy.npz`` / ``release_policy_config.yaml``: the release's image policy end to end
  (``make_release_policy``), its weights drawn from seeds, and its config at the fixture's sizes.

Remake (in a scratch venv; the project itself never depends on torch)::

    python3.11 -m venv /tmp/torchvenv && /tmp/torchvenv/bin/pip install torch==2.14.1 einops \\
        diffusers==0.11.1 huggingface_hub==0.25.2 hydra-core omegaconf dill wandb pandas zarr safetensors numba
    git clone https://github.com/real-stanford/diffusion_policy /tmp/dp_src
    git clone https://github.com/HzmSailor/HiPolicy /tmp/hipolicy
    /tmp/torchvenv/bin/python scripts/make_torch_fixtures.py --dp-src /tmp/dp_src \\
        --release-src /tmp/hipolicy/release/HiPolicy --out tests/fixtures/torch

Everything is seeded; the files differ between runs only in the checkpoint's pickled output directory.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile

import numpy as np

OBS_DIM, ACTION_DIM = 7, 4  # press_button's state and action
HORIZON, N_OBS, N_ACTION = 16, 2, 8
DOWN_DIMS, STEP_EMBED, KERNEL = [16, 32], 16, 5
BATCH = 3
RELEASE_ENCODER_SEED, RELEASE_UNET_SEED, DP_IMAGE_SEED = 58, 59, 60
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _np(t) -> np.ndarray:
    return t.detach().cpu().numpy().copy()


def make_dp(dp_src: str, out: str) -> None:
    import torch
    import hydra
    from omegaconf import OmegaConf

    sys.path.insert(0, dp_src)
    from diffusion_policy.workspace.train_diffusion_unet_lowdim_workspace import TrainDiffusionUnetLowdimWorkspace
    from diffusion_policy.model.common.normalizer import LinearNormalizer

    OmegaConf.register_new_resolver("eval", eval, replace=True)
    overrides = [f"task.obs_dim={OBS_DIM}", f"task.action_dim={ACTION_DIM}", f"horizon={HORIZON}",
                 f"n_obs_steps={N_OBS}", f"n_action_steps={N_ACTION}",
                 f"policy.model.down_dims=[{','.join(map(str, DOWN_DIMS))}]",
                 f"policy.model.diffusion_step_embed_dim={STEP_EMBED}", f"policy.model.kernel_size={KERNEL}",
                 "training.device=cpu", "logging.mode=disabled"]
    config_dir = os.path.join(os.path.abspath(dp_src), "diffusion_policy", "config")
    with hydra.initialize_config_dir(config_dir=config_dir, version_base=None):
        cfg = hydra.compose("train_diffusion_unet_lowdim_workspace", overrides=overrides)
    with tempfile.TemporaryDirectory() as tmp:
        ws = TrainDiffusionUnetLowdimWorkspace(cfg, output_dir=tmp)
        rng = np.random.default_rng(0)
        obs = rng.normal(size=(500, OBS_DIM)) * [0.3, 0.1, 2.0, 1.0, 0.5, 0.2, 0.0] + [0.1, -0.4, 0.0, 1.0, 2.0, 0, 0.75]
        act = rng.uniform(-1.5, 0.5, size=(500, ACTION_DIM)) * [1.0, 0.2, 3.0, 0.05]
        normalizer = LinearNormalizer()
        normalizer.fit({"obs": torch.from_numpy(obs.astype(np.float32)),
                        "action": torch.from_numpy(act.astype(np.float32))}, last_n_dims=1, mode="limits")
        ws.model.set_normalizer(normalizer)
        ws.ema_model.set_normalizer(normalizer)
        torch.manual_seed(1)
        with torch.no_grad():  # the EMA copy differs from the training weights, as after any training
            for p in ws.ema_model.model.parameters():
                p.add_(0.05 * torch.randn_like(p))
        path = ws.save_checkpoint(os.path.join(out, "dp_lowdim.ckpt"), use_thread=False)
        print("wrote", path)

    policy = ws.ema_model.eval()
    g = torch.Generator().manual_seed(2)
    x = torch.randn(BATCH, HORIZON, ACTION_DIM, generator=g)
    t = torch.tensor([0, 37, 99])
    raw_obs = torch.from_numpy(obs[:BATCH * N_OBS].reshape(BATCH, N_OBS, OBS_DIM).astype(np.float32))
    with torch.no_grad():
        nobs = policy.normalizer["obs"].normalize(raw_obs)
        global_cond = nobs[:, :N_OBS].reshape(BATCH, -1)
        eps = policy.model(x, t, global_cond=global_cond)
        scheduler = policy.noise_scheduler
        scheduler.set_timesteps(100)
        steps = {}
        for step in (99, 50, 1, 0):
            gen = torch.Generator().manual_seed(100 + step)
            noise = torch.randn(x.shape, generator=torch.Generator().manual_seed(100 + step))
            prev = scheduler.step(eps, step, x, generator=gen).prev_sample
            steps[f"ddpm_prev_{step}"] = _np(prev)
            steps[f"ddpm_noise_{step}"] = _np(noise)
        from diffusers.schedulers.scheduling_ddim import DDIMScheduler

        ddim = DDIMScheduler(num_train_timesteps=100, beta_schedule="squaredcos_cap_v2", clip_sample=True,
                             set_alpha_to_one=True, steps_offset=0, prediction_type="epsilon")
        ddim.set_timesteps(10)
        for step in (90, 40, 0):  # deterministic (eta = 0), as Diffusion Policy's DDIM configs run it
            steps[f"ddim_prev_{step}"] = _np(ddim.step(eps, step, x).prev_sample)
        raw_act = torch.from_numpy(act[:BATCH * HORIZON].reshape(BATCH, HORIZON, ACTION_DIM).astype(np.float32))
        nact = policy.normalizer["action"].normalize(raw_act)
        back = policy.normalizer["action"].unnormalize(nact)
    np.savez_compressed(os.path.join(out, "dp_lowdim.npz"), x=_np(x), t=_np(t), obs=_np(raw_obs),
                        nobs=_np(nobs), eps=_np(eps), action=_np(raw_act), naction=_np(nact), action_back=_np(back),
                        **steps)
    from safetensors.torch import save_file
    save_file({k: v.contiguous() for k, v in policy.state_dict().items()},
              os.path.join(out, "dp_lowdim_ema.safetensors"))
    make_dp_image(dp_src, out)


def _load_seeded():
    """``seeded_torch_state`` from ``hipolicy_jax/porting/encoders.py``, loaded by path (numpy only)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "porting_encoders", os.path.join(ROOT, "hipolicy_jax", "porting", "encoders.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.seeded_torch_state


def _seed_module(module, seed: int, skip: tuple[str, ...] = ()) -> dict[str, tuple[int, ...]]:
    """Overwrite ``module``'s tensors with ``seeded_torch_state(seed)`` (state-dict order); → their shapes."""
    import torch

    shapes = {k: tuple(v.shape) for k, v in module.state_dict().items()
              if not k.endswith("_dummy_variable") and not k.startswith(skip)}
    weights = _load_seeded()(shapes, seed)
    missing, unexpected = module.load_state_dict({k: torch.from_numpy(v) for k, v in weights.items()}, strict=False)
    assert not unexpected and all(k.endswith("_dummy_variable") or k.startswith(skip) for k in missing), \
        (missing, unexpected)
    return shapes


def make_dp_image(dp_src: str, out: str) -> None:
    """``dp_image.npz`` / ``dp_image_config.yaml``: Diffusion Policy's own ``DiffusionUnetImagePolicy`` (its
    ``MultiImageObsEncoder``: ResNet-18, GroupNorm, ImageNet normalisation, a 52 px crop of 56 px images, centre crop
    in eval; ``head_cam`` and ``agent_pos`` (4); 2 observation steps, horizon 16, 8 executed), weights drawn by
    ``seeded_torch_state`` (redrawn by the test), a fitted ``LinearNormalizer`` with the image range normaliser. The
    reference follows ``predict_action``'s conditioning: normalise, the first ``n_obs_steps`` frames through the
    encoder, features flattened frame-major into the global condition, then the U-Net."""
    import torch
    from diffusers.schedulers.scheduling_ddpm import DDPMScheduler
    from diffusion_policy.common.normalize_util import get_image_range_normalizer
    from diffusion_policy.model.common.normalizer import LinearNormalizer
    from diffusion_policy.model.vision.model_getter import get_resnet
    from diffusion_policy.model.vision.multi_image_obs_encoder import MultiImageObsEncoder
    from diffusion_policy.policy.diffusion_unet_image_policy import DiffusionUnetImagePolicy

    size, low, crop = 56, 4, 52
    shape_meta = {"obs": {"head_cam": {"shape": [3, size, size], "type": "rgb"},
                          "agent_pos": {"shape": [low], "type": "low_dim"}}, "action": {"shape": [ACTION_DIM]}}
    enc = MultiImageObsEncoder(shape_meta, get_resnet("resnet18"), resize_shape=None, crop_shape=(crop, crop),
                               random_crop=True, use_group_norm=True, share_rgb_model=False, imagenet_norm=True)
    scheduler = DDPMScheduler(num_train_timesteps=100, beta_start=0.0001, beta_end=0.02,
                              beta_schedule="squaredcos_cap_v2", variance_type="fixed_small", clip_sample=True,
                              prediction_type="epsilon")
    policy = DiffusionUnetImagePolicy(shape_meta, scheduler, enc, horizon=HORIZON, n_action_steps=N_ACTION,
                                      n_obs_steps=N_OBS, num_inference_steps=100, obs_as_global_cond=True,
                                      diffusion_step_embed_dim=STEP_EMBED, down_dims=DOWN_DIMS, kernel_size=KERNEL,
                                      n_groups=8, cond_predict_scale=True)
    shapes = _seed_module(policy, DP_IMAGE_SEED, skip=("normalizer.",))
    rng = np.random.default_rng(5)
    normalizer = LinearNormalizer()
    normalizer.fit({"agent_pos": torch.from_numpy((rng.standard_normal((300, low)) * [2.0, 0.3, 1.0, 0.05]
                                                   ).astype(np.float32)),
                    "action": torch.from_numpy(rng.uniform(-2, 1, (300, ACTION_DIM)).astype(np.float32))},
                   last_n_dims=1, mode="limits")
    normalizer["head_cam"] = get_image_range_normalizer()
    policy.set_normalizer(normalizer)
    policy.eval()
    b = 2
    images = rng.integers(0, 256, (b, N_OBS, size, size, 3), dtype=np.uint8)
    agent_pos = (rng.standard_normal((b, N_OBS, low)) * [2.0, 0.3, 1.0, 0.05]).astype(np.float32)
    x = torch.from_numpy(rng.standard_normal((b, HORIZON, ACTION_DIM)).astype(np.float32))
    t = torch.tensor([12, 88])
    with torch.no_grad():
        nobs = policy.normalizer.normalize({"head_cam": torch.from_numpy(np.moveaxis(images, -1, 2) / 255),
                                            "agent_pos": torch.from_numpy(agent_pos)})
        this = {k: v[:, :N_OBS].reshape(-1, *v.shape[2:]) for k, v in nobs.items()}
        cond = policy.obs_encoder(this).reshape(b, -1)
        y = policy.model(x, t, local_cond=None, global_cond=cond)
    norm = {f"normalizer.{k}": _np(v) for k, v in policy.normalizer.state_dict().items()
            if not k.startswith("params_dict.head_cam")}
    np.savez_compressed(os.path.join(out, "dp_image.npz"), images=images, agent_pos=agent_pos, x=_np(x), t=_np(t),
                        cond=_np(cond), y=_np(y), seed=DP_IMAGE_SEED, param_names=np.array(list(shapes)),
                        param_shapes=np.array([",".join(map(str, v)) for v in shapes.values()]), **norm)
    import yaml

    config = {"horizon": HORIZON, "n_obs_steps": N_OBS, "n_action_steps": N_ACTION, "n_latency_steps": 0,
              "obs_as_global_cond": True, "shape_meta": shape_meta,
              "policy": {"_target_": "diffusion_policy.policy.diffusion_unet_image_policy.DiffusionUnetImagePolicy",
                         "noise_scheduler": {"_target_": "diffusers.schedulers.scheduling_ddpm.DDPMScheduler",
                                             **{k: scheduler.config[k] for k in (
                                                 "num_train_timesteps", "beta_start", "beta_end", "beta_schedule",
                                                 "variance_type", "clip_sample", "prediction_type")}},
                         "obs_encoder": {"rgb_model": {"name": "resnet18", "weights": None}, "resize_shape": None,
                                         "crop_shape": [crop, crop], "random_crop": True, "use_group_norm": True,
                                         "share_rgb_model": False, "imagenet_norm": True},
                         "horizon": HORIZON, "n_action_steps": N_ACTION, "n_obs_steps": N_OBS,
                         "num_inference_steps": 100, "obs_as_global_cond": True,
                         "diffusion_step_embed_dim": STEP_EMBED, "down_dims": DOWN_DIMS, "kernel_size": KERNEL,
                         "n_groups": 8, "cond_predict_scale": True}}
    with open(os.path.join(out, "dp_image_config.yaml"), "w") as f:
        yaml.safe_dump(config, f, sort_keys=False)
    print("wrote", os.path.join(out, "dp_image.npz"), "and dp_image_config.yaml")


def make_release(dp_src: str, release_src: str, out: str) -> None:
    import torch

    os.environ["HIPOLICY_BENCHMARK"] = "robotwin_v2"
    with tempfile.TemporaryDirectory() as tmp:
        shutil.copytree(os.path.join(dp_src, "diffusion_policy"), os.path.join(tmp, "diffusion_policy"))
        for name in ("conditional_unet1d.py", "cross_attention.py"):
            shutil.copy(os.path.join(release_src, "policy", "diffusion_policy", "model", "diffusion", name),
                        os.path.join(tmp, "diffusion_policy", "model", "diffusion", name))
        sys.path[:0] = [tmp, release_src]
        from diffusion_policy.model.diffusion.conditional_unet1d import ConditionalUnet1D

        torch.manual_seed(0)
        feat = 3 * OBS_DIM  # three frames of a 7-D state per stride
        net = ConditionalUnet1D(input_dim=ACTION_DIM, actual_horizon=8, global_cond_dim=feat,
                                diffusion_step_embed_dim=STEP_EMBED, down_dims=DOWN_DIMS, kernel_size=KERNEL,
                                n_groups=8, cond_predict_scale=True).eval()
        g = torch.Generator().manual_seed(3)
        x = torch.randn(BATCH, 24, ACTION_DIM, generator=g)
        t = torch.tensor([5, 60, 99])
        conds = [torch.randn(BATCH, feat, generator=g) for _ in range(3)]  # long, mid, short
        with torch.no_grad():
            y = net(x, t, global_cond_long=conds[0], global_cond_mid=conds[1], global_cond_short=conds[2])
            fusion = net.down_modules[0][0].global_feature_extractor
            tokens_in = x.transpose(1, 2)  # (B, A, 24): the block's input layout
            glob = fusion(tokens_in)
            other = torch.randn(5, ACTION_DIM, 24, generator=g)
            glob_other = fusion(other)
            # the same module's attention over each sample's own tokens: sequence-first input (M+1, B, D)
            b, c, tt = tokens_in.shape
            lc = tt // 3
            segs = [tokens_in[:, :, i * lc:(i + 1) * lc].reshape(b, -1) for i in range(3)]
            tokens = torch.stack([fusion.cls_tokens.expand(b, -1, -1)[:, 0]] + segs, dim=0)  # (4, B, D)
            per_sample = fusion.cross_attention(tokens, tokens, tokens)[0][0].reshape(b, c, lc)
        sd = {f"sd/{k}": _np(v) for k, v in net.state_dict().items()}
        np.savez_compressed(os.path.join(out, "release_unet.npz"), x=_np(x), t=_np(t), cond=np.stack(
            [_np(c) for c in conds], axis=1), y=_np(y), fusion_in=_np(tokens_in), fusion_out=_np(glob),
            fusion_other_in=_np(other), fusion_other_out=_np(glob_other), fusion_per_sample=_np(per_sample), **sd)
        print("wrote", os.path.join(out, "release_unet.npz"))
        make_release_policy(out)  # with the release's modules on sys.path


def make_release_policy(out: str) -> None:
    """The release's image policy end to end (``release_policy.npz``): Diffusion Policy's ``MultiImageObsEncoder``
    with the release's settings (``configs/robotwin_v2/dp.yaml``: ResNet-18, GroupNorm, ImageNet normalisation, no
    crop) for ``head_cam`` (3 x 56 x 56) and ``agent_pos`` (4), the release's hierarchical U-Net conditioned on three
    frames per stride, and ``LinearNormalizer`` + the image range normaliser. Weights are drawn by
    ``seeded_torch_state`` (numpy; the test redraws them: 11 M encoder weights are not stored) and written into the
    upstream modules. The forward pass follows the release's ``predict_action`` for robotwin_v2: normalise, frames
    [0, 3, 6] / [2, 4, 6] / [4, 5, 6] of the 7 observed ones through the encoder, each stride's features flattened
    frame-major into its condition, then the U-Net."""
    import torch
    from diffusion_policy.common.normalize_util import get_image_range_normalizer
    from diffusion_policy.model.common.normalizer import LinearNormalizer
    from diffusion_policy.model.diffusion.conditional_unet1d import ConditionalUnet1D
    from diffusion_policy.model.vision.model_getter import get_resnet
    from diffusion_policy.model.vision.multi_image_obs_encoder import MultiImageObsEncoder

    size, low = 56, 4
    shape_meta = {"obs": {"head_cam": {"shape": [3, size, size], "type": "rgb"},
                          "agent_pos": {"shape": [low], "type": "low_dim"}}, "action": {"shape": [ACTION_DIM]}}
    enc = MultiImageObsEncoder(shape_meta, get_resnet("resnet18"), resize_shape=None, crop_shape=None,
                               random_crop=True, use_group_norm=True, share_rgb_model=False, imagenet_norm=True)
    net = ConditionalUnet1D(input_dim=ACTION_DIM, actual_horizon=8, global_cond_dim=3 * (512 + low),
                            diffusion_step_embed_dim=STEP_EMBED, down_dims=DOWN_DIMS, kernel_size=KERNEL, n_groups=8,
                            cond_predict_scale=True)
    shapes = {}
    for prefix, module, seed in (("obs_encoder.", enc, RELEASE_ENCODER_SEED), ("model.", net, RELEASE_UNET_SEED)):
        shapes.update({prefix + k: v for k, v in _seed_module(module, seed).items()})
    enc.eval()
    net.eval()
    rng = np.random.default_rng(4)
    b = 2
    images = rng.integers(0, 256, (b, 7, size, size, 3), dtype=np.uint8)
    agent_pos = (rng.standard_normal((b, 7, low)) * [1.0, 0.5, 2.0, 0.1]).astype(np.float32)
    normalizer = LinearNormalizer()
    normalizer.fit({"agent_pos": torch.from_numpy(
        (rng.standard_normal((300, low)) * [1.0, 0.5, 2.0, 0.1]).astype(np.float32)),
        "action": torch.from_numpy(rng.uniform(-1, 1, (300, ACTION_DIM)).astype(np.float32))},
        last_n_dims=1, mode="limits")
    normalizer["head_cam"] = get_image_range_normalizer()
    x = torch.from_numpy(rng.standard_normal((b, 24, ACTION_DIM)).astype(np.float32))
    t = torch.tensor([3, 71])
    with torch.no_grad():
        nobs = normalizer.normalize({"head_cam": torch.from_numpy(np.moveaxis(images, -1, 2) / 255),
                                     "agent_pos": torch.from_numpy(agent_pos)})
        conds = []
        for idx in ([0, 3, 6], [2, 4, 6], [4, 5, 6]):  # long, mid, short
            this = {k: v[:, idx].reshape(-1, *v.shape[2:]) for k, v in nobs.items()}
            conds.append(enc(this).reshape(b, -1))
        y = net(x, t, global_cond_long=conds[0], global_cond_mid=conds[1], global_cond_short=conds[2])
    norm = {f"normalizer.params_dict.{k}": _np(v) for k, v in normalizer.state_dict().items()
            if k.startswith("params_dict.") and not k.startswith("params_dict.head_cam")}
    norm = {k.replace("normalizer.params_dict.params_dict.", "normalizer.params_dict."): v for k, v in norm.items()}
    np.savez_compressed(os.path.join(out, "release_policy.npz"), images=images, agent_pos=agent_pos, x=_np(x),
                        t=_np(t), cond=np.stack([_np(c) for c in conds], 1), y=_np(y),
                        encoder_seed=RELEASE_ENCODER_SEED, unet_seed=RELEASE_UNET_SEED,
                        param_names=np.array(list(shapes)),
                        param_shapes=np.array([",".join(map(str, v)) for v in shapes.values()]), **norm)
    import yaml

    config = {  # the release's configs/robotwin_v2/dp.yaml at the fixture's sizes: what the converter reads
        "horizon": 29, "n_obs_steps": 7, "n_action_steps": 8, "n_latency_steps": 0, "obs_as_global_cond": True,
        "shape_meta": shape_meta,
        "policy": {"_target_": "diffusion_policy.policy.diffusion_unet_image_policy.DiffusionUnetImagePolicy",
                   "noise_scheduler": {"_target_": "diffusers.schedulers.scheduling_ddpm.DDPMScheduler",
                                       "num_train_timesteps": 100, "beta_start": 0.0001, "beta_end": 0.02,
                                       "beta_schedule": "squaredcos_cap_v2", "variance_type": "fixed_small",
                                       "clip_sample": True, "prediction_type": "epsilon"},
                   "obs_encoder": {"rgb_model": {"name": "resnet18", "weights": None}, "resize_shape": None,
                                   "crop_shape": None, "random_crop": True, "use_group_norm": True,
                                   "share_rgb_model": False, "imagenet_norm": True},
                   "horizon": 29, "n_action_steps": 8, "n_obs_steps": 7, "num_inference_steps": 100,
                   "obs_as_global_cond": True, "diffusion_step_embed_dim": STEP_EMBED, "down_dims": DOWN_DIMS,
                   "kernel_size": KERNEL, "n_groups": 8, "cond_predict_scale": True}}
    with open(os.path.join(out, "release_policy_config.yaml"), "w") as f:
        yaml.safe_dump(config, f, sort_keys=False)
    print("wrote", os.path.join(out, "release_policy.npz"), "and release_policy_config.yaml")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dp-src", required=True, help="a checkout of real-stanford/diffusion_policy")
    p.add_argument("--release-src", required=True, help="the HiPolicy release folder (release/HiPolicy)")
    p.add_argument("--out", default="tests/fixtures/torch")
    p.add_argument("--part", choices=("all", "dp", "release"), default="all")
    a = p.parse_args()
    os.makedirs(a.out, exist_ok=True)
    dp_src, release_src, out = (os.path.abspath(x) for x in (a.dp_src, a.release_src, a.out))
    if a.part == "all":
        for part in ("dp", "release"):
            subprocess.run([sys.executable, __file__, "--dp-src", dp_src, "--release-src", release_src, "--out", out,
                            "--part", part], check=True)
    elif a.part == "dp":
        make_dp(dp_src, out)
    else:
        make_release(dp_src, release_src, out)


if __name__ == "__main__":
    main()
