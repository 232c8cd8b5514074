"""PyTorch policies run in JAX: Diffusion Policy's and the HiPolicy release's weights give their numbers to 1e-5.

Fixtures (``tests/fixtures/torch/``, made by ``scripts/make_torch_fixtures.py`` with the unmodified upstream code):
``dp_lowdim.ckpt`` (a Diffusion Policy workspace checkpoint written by its own ``save_checkpoint``), its EMA policy's
state dict as ``dp_lowdim_ema.safetensors`` and its outputs ``dp_lowdim.npz``; ``release_unet.npz`` (the release's
hierarchical U-Net: weights, inputs, output, fusion outputs); ``release_policy.npz`` (the release's image policy
end to end, weights redrawn from seeds by ``porting.encoders.seeded_torch_state``).
"""

from __future__ import annotations

import io
import os
import pathlib
import pickle
import subprocess
import sys
import zipfile

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml

from hipolicy_jax.config import ChunkConfig, ModelConfig
from hipolicy_jax.heads.diffusion import reverse_table, reverse_step
from hipolicy_jax.models.policy_net import PolicyNet
from hipolicy_jax.models.unet import ConditionalUnet1D, SegmentFusion
from hipolicy_jax.porting.convert import convert, write_run
from hipolicy_jax.porting.encoders import seeded_torch_state
from hipolicy_jax.porting.torch_checkpoint import (plain_config, read_safetensors, read_torch_file,
                                                   resolve_config, safe_eval)
from hipolicy_jax.porting.unet import unet_params, unet_shape

FIX = pathlib.Path(__file__).parent / "fixtures" / "torch"
ROOT = pathlib.Path(__file__).parent.parent
TOL = 1e-5  # float32; measured: U-Nets 1.0e-6 / 1.1e-6, the release's image policy 3.1e-6 (outputs of magnitude 1-5)


def _load(name: str) -> dict:
    with np.load(FIX / name) as d:
        return {k: d[k] for k in d.files}


@pytest.fixture(scope="module")
def release_unet():
    d = _load("release_unet.npz")
    return d, {k[3:]: v for k, v in d.items() if k.startswith("sd/")}


def _release_net(kind: str) -> ConditionalUnet1D:
    return ConditionalUnet1D(down_dims=(16, 32), kernel_size=5, step_embed_dim=16, num_freqs=3, chunk_len=8,
                             fusion_kind=kind)


def _release_out(params, d, kind="release") -> np.ndarray:
    return np.asarray(_release_net(kind).apply({"params": params}, jnp.asarray(d["x"]), jnp.asarray(d["t"]),
                                               jnp.asarray(d["cond"])))


# ---------------------------------------------------------------- the release's U-Net and fusion


def test_release_unet_equals_the_release(release_unet):
    d, sd = release_unet
    assert unet_shape(sd, "") == {"down_dims": (16, 32), "kernel_size": 5, "step_embed_dim": 16, "action_dim": 4,
                                  "cond_dim": 21, "hierarchical": True, "local_cond": False}
    y = _release_out(unet_params(sd, "", fusion_kind="release"), d)
    assert np.abs(y - d["y"]).max() < TOL
    assert np.abs(d["y"]).max() > 0.5  # a real signal, not zeros


def test_release_fusion_is_a_learned_constant(release_unet):
    """The release's fusion output does not depend on its input or batch (upstream outputs), and ours reproduces
    it; our per-sample attention reproduces the same torch module fed sequence-first."""
    d, sd = release_unet
    ref = d["fusion_out"]  # (B, C, L) from the release module
    assert np.abs(ref - ref[:1]).max() == 0.0
    assert np.abs(d["fusion_other_out"] - ref[:1]).max() < 1e-6  # other input, other batch size
    for kind, want in (("release", ref), ("attention", d["fusion_per_sample"])):
        p = unet_params(sd, "", fusion_kind=kind)["down0_res0"]["fusion"]
        got = SegmentFusion(3, 8, kind=kind).apply({"params": p}, jnp.asarray(d["fusion_in"]).transpose(0, 2, 1))
        assert np.abs(np.asarray(got) - want.transpose(0, 2, 1)).max() < TOL, kind
    per_sample = d["fusion_per_sample"]
    assert np.abs(per_sample - per_sample[:1]).max() > 0.1  # real attention differs between samples


def test_per_sample_attention_changes_the_output(release_unet):
    """Same weights, the fusion computed as the paper describes: the U-Net's output moves by O(0.1), so the
    release's constant and real attention are different functions."""
    d, sd = release_unet
    y = _release_out(unet_params(sd, "", fusion_kind="attention"), d, "attention")
    assert np.abs(y - d["y"]).max() > 0.05


@pytest.mark.parametrize("wrong", ["upsample_taps_not_reversed", "conv_kernel_transposed", "film_rows_swapped",
                                   "fusion_value_as_query"])
def test_one_weight_mapped_wrongly_fails(release_unet, wrong):
    """The equivalence test can fail: each of these single mapping mistakes moves the output far beyond 1e-5."""
    d, sd = release_unet
    p = unet_params(sd, "", fusion_kind="release")
    if wrong == "upsample_taps_not_reversed":
        p["up0_upsample"]["kernel"] = p["up0_upsample"]["kernel"][::-1]
    elif wrong == "conv_kernel_transposed":
        k = p["mid_res0"]["block0"]["conv"]["kernel"]
        p["mid_res0"]["block0"]["conv"]["kernel"] = k.transpose(0, 2, 1)
    elif wrong == "film_rows_swapped":  # scale and bias halves exchanged
        k, b = p["down1_res0"]["film"]["kernel"], p["down1_res0"]["film"]["bias"]
        c = k.shape[1] // 2
        p["down1_res0"]["film"] = {"kernel": np.concatenate([k[:, c:], k[:, :c]], 1),
                                   "bias": np.concatenate([b[c:], b[:c]])}
    else:
        w = sd["down_modules.0.0.global_feature_extractor.cross_attention.in_proj_weight"]
        dim = w.shape[1]
        p["down0_res0"]["fusion"]["attention"]["value"]["kernel"] = w[:dim].T.reshape(dim, 8, dim // 8)
    assert np.abs(_release_out(p, d) - d["y"]).max() > 100 * TOL


def test_unet_params_names_the_bad_tensor(release_unet):
    _, sd = release_unet
    bad = dict(sd)
    del bad["mid_modules.1.cond_encoder.1.weight"]
    with pytest.raises(ValueError, match=r"unet: state dict has no 'mid_modules\.1\.cond_encoder\.1\.weight'"):
        unet_params(bad, "")
    bad = {**sd, "final_conv.1.weight": sd["final_conv.1.weight"][:2]}
    with pytest.raises(ValueError, match=r"'final_conv\.1\.weight' has shape \(2, 16, 1\), expected \(4, 16, 1\)"):
        unet_params(bad, "")
    with pytest.raises(ValueError, match=r"1 tensors of the state dict were not mapped, e.g. \['extra.weight'\]"):
        unet_params({**sd, "extra.weight": np.zeros(3)}, "")
    with pytest.raises(ValueError, match=r"no model\.down_modules\.\* in the state dict; is the prefix right"):
        unet_shape(sd, "model.")


def test_fusion_kind_config():
    assert ModelConfig().fusion_kind == "attention"
    with pytest.raises(ValueError, match=r"model\.fusion_kind: must be 'attention' or 'release', got 'x'"):
        ModelConfig(fusion_kind="x")
    with pytest.raises(ValueError, match=r"model\.fusion_token_dim: the release's fusion .* got 64"):
        ModelConfig(fusion_kind="release", fusion_token_dim=64)


# ---------------------------------------------------------------- Diffusion Policy's checkpoint


@pytest.fixture(scope="module")
def dp():
    return convert("dp", str(FIX / "dp_lowdim.ckpt")), _load("dp_lowdim.npz")


def _dp_eps(conv, f) -> np.ndarray:
    net = PolicyNet(conv.cfg, conv.action_dim)
    nobs = conv.normalizer.normalize("state", f["obs"])
    cond = net.apply(conv.variables, {"state": jnp.asarray(nobs)[:, None]}, method=net.encode)
    return np.asarray(net.apply(conv.variables, jnp.asarray(f["x"]), jnp.asarray(f["t"]), cond, method=net.denoise))


def test_dp_checkpoint_converts_with_its_settings(dp):
    conv, _ = dp
    assert conv.cfg.chunk == ChunkConfig(strides=(1,), obs_horizon=2, chunk_len=16, action_offset=-1, exec_len=8)
    assert (conv.cfg.chunk.exec_start, conv.cfg.chunk.exec_steps) == (1, 8)  # DP's start = To - 1
    assert conv.cfg.model.unet_dims == (16, 32) and conv.cfg.model.unet_step_embed == 16
    assert conv.cfg.encoder.state_encoder == "identity" and conv.obs_shapes == {"state": (7,)}
    d = conv.cfg.diffusion
    assert (d.num_train_steps, d.beta_schedule, d.prediction_type, d.clip_sample) == (100, "squaredcos_cap_v2",
                                                                                       "epsilon", True)
    assert (conv.inference.sampler, conv.inference.num_steps) == ("ddpm", 100)
    assert conv.source["weights"] == "ema_model"


def test_dp_denoiser_and_normaliser_equal_the_original(dp):
    conv, f = dp
    assert np.abs(np.asarray(conv.normalizer.normalize("state", f["obs"])) - f["nobs"]).max() < TOL
    na = np.asarray(conv.normalizer.normalize("action", f["action"]))
    assert np.abs(na - f["naction"]).max() < TOL
    assert np.abs(np.asarray(conv.normalizer.unnormalize("action", na)) - f["action_back"]).max() < TOL
    assert np.abs(_dp_eps(conv, f) - f["eps"]).max() < TOL


def test_dp_training_weights_are_not_the_evaluated_ones(dp):
    """The fixture's EMA weights were moved away from the training weights: only the EMA copy gives DP's numbers."""
    _, f = dp
    model = convert("dp", str(FIX / "dp_lowdim.ckpt"), weights="model")
    assert model.source["weights"] == "model"
    assert np.abs(_dp_eps(model, f) - f["eps"]).max() > 100 * TOL


@pytest.mark.parametrize("t", [99, 50, 1, 0])
def test_dp_ddpm_step_equals_diffusers(dp, t):
    """One DDPM step of DP's DDPMScheduler (fixed_small variance, clipped x0) with the noise it drew."""
    conv, f = dp
    table = reverse_table(conv.cfg.diffusion, "ddpm", 100)
    row = jax.tree.map(lambda a: a[99 - t], table)
    assert int(row.time) == t
    prev = reverse_step(conv.cfg.diffusion, row, jnp.asarray(f["x"]), jnp.asarray(f["eps"]),
                        jnp.asarray(f[f"ddpm_noise_{t}"]))
    assert np.abs(np.asarray(prev) - f[f"ddpm_prev_{t}"]).max() < TOL


@pytest.mark.parametrize("t", [90, 40, 0])
def test_ddim_step_equals_diffusers(dp, t):
    """One step of diffusers' DDIMScheduler (10 steps, eta 0, clipped x0, set_alpha_to_one) on DP's model output."""
    conv, f = dp
    table = reverse_table(conv.cfg.diffusion, "ddim", 10)
    i = int(np.flatnonzero(np.asarray(table.time) == t)[0])
    row = jax.tree.map(lambda a: a[i], table)
    prev = reverse_step(conv.cfg.diffusion, row, jnp.asarray(f["x"]), jnp.asarray(f["eps"]), None)
    assert np.abs(np.asarray(prev) - f[f"ddim_prev_{t}"]).max() < TOL


def test_safetensors_with_a_config_equals_the_ckpt(dp, tmp_path):
    conv, f = dp
    cfg = resolve_config(plain_config(read_torch_file(str(FIX / "dp_lowdim.ckpt"))["cfg"]))
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(cfg))
    st = convert("dp", str(FIX / "dp_lowdim_ema.safetensors"), str(tmp_path / "config.yaml"))
    assert st.cfg == conv.cfg
    assert np.abs(_dp_eps(st, f) - f["eps"]).max() < TOL
    with pytest.raises(ValueError, match=r"--config: a safetensors file holds weights only"):
        convert("dp", str(FIX / "dp_lowdim_ema.safetensors"))
    with pytest.raises(ValueError, match=r"has no fusion modules .* convert it as dp"):
        convert("hipolicy-release", str(FIX / "dp_lowdim.ckpt"))


# ---------------------------------------------------------------- the release's image policy end to end


def _seeded_policy_files(tmp_path, name: str, seeds: dict[str, str]) -> tuple[str, str, dict]:
    """``(safetensors, config)`` of the fixture ``name``: its weights redrawn per prefix from its seeds (``seeds``:
    {prefix: npz key of the seed}), its normaliser as stored, its config beside it."""
    from safetensors.numpy import save_file

    f = _load(f"{name}.npz")
    shapes = {n: tuple(int(x) for x in s.split(",")) for n, s in zip(f["param_names"], f["param_shapes"])}
    sd = {k: v for k, v in f.items() if k.startswith("normalizer.")}
    for prefix, seed in seeds.items():
        part = {k[len(prefix):]: v for k, v in shapes.items() if k.startswith(prefix)}
        sd.update({prefix + k: v for k, v in seeded_torch_state(part, int(f[seed])).items()})
    save_file(sd, str(tmp_path / f"{name}.safetensors"))
    return str(tmp_path / f"{name}.safetensors"), str(FIX / f"{name}_config.yaml"), f


def _release_policy_files(tmp_path) -> tuple[str, str, dict]:
    return _seeded_policy_files(tmp_path, "release_policy", {"obs_encoder.": "encoder_seed", "model.": "unet_seed"})


def test_dp_image_policy_equals_diffusion_policy(tmp_path):
    """DP's own DiffusionUnetImagePolicy: its ResNet-18 encoder with a 52 px centre crop (eval) of 56 px images, two
    observed frames, the U-Net; condition and output equal."""
    weights, config, f = _seeded_policy_files(tmp_path, "dp_image", {"": "seed"})
    conv = convert("dp", weights, config)
    assert conv.cfg.chunk == ChunkConfig(strides=(1,), obs_horizon=2, chunk_len=16, action_offset=-1, exec_len=8)
    assert conv.cfg.encoder.image_encoder == "resnet_avgpool" and conv.cfg.encoder.crop_size == 52
    assert conv.obs_shapes == {"state": (4,), "image": (56, 56, 3)}
    nobs = conv.normalizer.normalize_obs({"state": f["agent_pos"][:, None], "image": f["images"][:, None]})
    net = PolicyNet(conv.cfg, conv.action_dim)
    cond = net.apply(conv.variables, nobs, method=net.encode)
    assert np.abs(np.asarray(cond)[:, 0] - f["cond"]).max() < TOL
    y = net.apply(conv.variables, jnp.asarray(f["x"]), jnp.asarray(f["t"]), cond, method=net.denoise)
    assert np.abs(np.asarray(y) - f["y"]).max() < TOL
    assert np.abs(f["y"]).max() > 0.5


def test_unsupported_checkpoints_are_refused_naming_why(tmp_path):
    weights, config, _ = _seeded_policy_files(tmp_path, "dp_image", {"": "seed"})
    cfg = yaml.safe_load(open(config))
    for change, msg in (
            (("policy", "_target_", "diffusion_policy.policy.diffusion_transformer_lowdim_policy.X"),
             r"policy\._target_ 'diffusion_policy\.policy\.diffusion_transformer_lowdim_policy\.X' is not supported"),
            (("policy", "noise_scheduler", {"_target_": "diffusers.schedulers.scheduling_ddpm.DDPMScheduler",
                                            "variance_type": "fixed_small_log"}),
             r"variance_type 'fixed_small_log': only 'fixed_small'"),
            (("policy", "obs_encoder", {**cfg["policy"]["obs_encoder"], "resize_shape": [40, 40]}),
             r"resize_shape \[40, 40\] is not implemented")):
        bad = yaml.safe_load(open(config))
        bad[change[0]][change[1]] = change[2]
        (tmp_path / "bad.yaml").write_text(yaml.safe_dump(bad))
        with pytest.raises(ValueError, match=msg):
            convert("dp", weights, str(tmp_path / "bad.yaml"))
    with pytest.raises(ValueError, match=r"kind: must be 'dp' or 'hipolicy-release', got 'x'"):
        convert("x", weights, config)


def test_import_refuses_a_task_of_other_sizes(tmp_path):
    from experiments.import_checkpoint import ImportArgs, main

    with pytest.raises(ValueError, match=r"task: stack_cubes has actions of 4 and states of 13; the checkpoint's "
                                         r"policy takes actions of 4 and states of 7"):
        main(ImportArgs("dp", str(FIX / "dp_lowdim.ckpt"), str(tmp_path / "run"), task="stack_cubes"))
    assert not (tmp_path / "run").exists()


def test_release_image_policy_equals_the_release(tmp_path):
    weights, config, f = _release_policy_files(tmp_path)
    conv = convert("hipolicy-release", weights, config)
    assert conv.cfg.chunk.strides == (1, 2, 3) and conv.cfg.chunk.action_offset == 1
    assert conv.cfg.model.fusion_kind == "release" and conv.cfg.encoder.image_encoder == "resnet_avgpool"
    idx = np.array([[0, 3, 6], [2, 4, 6], [4, 5, 6]])  # the release's frames per stride of its 7 observed ones
    nobs = conv.normalizer.normalize_obs({"state": f["agent_pos"][:, idx], "image": f["images"][:, idx]})
    net = PolicyNet(conv.cfg, conv.action_dim)
    cond = net.apply(conv.variables, nobs, method=net.encode)
    assert np.abs(np.asarray(cond) - f["cond"]).max() < TOL
    y = net.apply(conv.variables, jnp.asarray(f["x"]), jnp.asarray(f["t"]), cond, method=net.denoise)
    assert np.abs(np.asarray(y) - f["y"]).max() < TOL


# ---------------------------------------------------------------- the .ckpt reader never runs code


class _Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned",))


def _torch_like_zip(path, obj) -> None:
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("archive/data.pkl", pickle.dumps(obj, protocol=2))
        z.writestr("archive/byteorder", "little")


def test_reader_refuses_code_in_a_checkpoint(tmp_path):
    _torch_like_zip(tmp_path / "evil.ckpt", {"cfg": {}, "state_dicts": {"model": _Evil()}})
    with pytest.raises(ValueError, match=r"refers to (posix|os|nt)\.system, which this reader does not load"):
        read_torch_file(str(tmp_path / "evil.ckpt"))
    (tmp_path / "plain.pkl").write_bytes(pickle.dumps({"a": 1}))
    with pytest.raises(ValueError, match=r"is not a torch zip archive"):
        read_torch_file(str(tmp_path / "plain.pkl"))
    with pytest.raises(FileNotFoundError, match=r"checkpoint: .*missing\.ckpt does not exist"):
        read_torch_file(str(tmp_path / "missing.ckpt"))


def test_reader_reads_every_tensor_of_the_checkpoint():
    payload = read_torch_file(str(FIX / "dp_lowdim.ckpt"))
    st = read_safetensors(str(FIX / "dp_lowdim_ema.safetensors"))
    ema = payload["state_dicts"]["ema_model"]
    assert set(st) <= set(ema) and all(np.array_equal(ema[k], st[k]) for k in st)
    opt = payload["state_dicts"]["optimizer"]
    assert opt["param_groups"][0]["betas"] == [0.95, 0.999] or tuple(opt["param_groups"][0]["betas"]) == (0.95, 0.999)


def test_config_resolution_is_restricted():
    cfg = resolve_config({"a": 2, "b": "x", "c": "${eval:${b} + 'y'}", "d": "n${a}m",
                          "e": "${eval: ${a} * 3 if ${a} > 1 else None}", "f": "${eval:'${a}+${e}'}",
                          "g": "${now:%Y}", "h": "${eval: None if False else None}"})
    assert cfg == {"a": 2, "b": "x", "c": "xy", "d": "n2m", "e": 6, "f": 8, "g": "${now:%Y}", "h": None}
    with pytest.raises(ValueError, match=r"uses Call, which is not evaluated here"):
        safe_eval("__import__('os').system('echo pwned')")
    with pytest.raises(ValueError, match=r"uses Name"):
        safe_eval("open")
    with pytest.raises(ValueError, match=r"\$\{nope\} refers to a key that does not exist"):
        resolve_config({"a": "${nope}"})


# ---------------------------------------------------------------- a DP checkpoint through the CLI


def test_dp_checkpoint_evaluates_and_serves_through_the_cli(tmp_path):
    """import_checkpoint writes a run; evaluate runs it closed loop on press_button; the policy server loads it
    and its decision executes DP's window of the chunk (8 actions from the current frame)."""
    out = tmp_path / "run"
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    r = subprocess.run([sys.executable, "-m", "experiments.import_checkpoint", "dp", str(FIX / "dp_lowdim.ckpt"),
                        str(out), "--task", "press_button"], cwd=ROOT, env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "chunk 16 from offset -1 (8 executed)" in r.stdout
    r = subprocess.run([sys.executable, "-m", "experiments.import_checkpoint", "dp", str(FIX / "dp_lowdim.ckpt"),
                        str(out)], cwd=ROOT, env=env, capture_output=True, text=True)
    assert r.returncode == 1 and "already holds checkpoints" in r.stderr
    r = subprocess.run([sys.executable, "-m", "experiments.evaluate", "--checkpoint", str(out), "--episodes", "2",
                        "--inference.sampler", "ddim", "--inference.num-steps", "3", "--video", "none"], cwd=ROOT, env=env,
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "press_button @ step 0, 2 episodes" in r.stdout

    r = subprocess.run([sys.executable, "-m", "experiments.calibrate", "--checkpoint", str(out), "--source",
                        "rollouts", "--episodes", "1", "--inference.sampler", "ddim", "--inference.num-steps", "3"],
                       cwd=ROOT, env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (out / "calibration.json").is_file()  # one stride: no thresholds to set, [-inf, inf]

    from hipolicy_jax.config import InferenceConfig
    from hipolicy_jax.deploy.client import PolicyClient
    from hipolicy_jax.deploy.server import PolicyServer, ServerConfig
    from hipolicy_jax.runs.serve import run_backend

    backend = run_backend(str(out), InferenceConfig(sampler="ddim", num_steps=3), None)
    meta = backend.metadata
    assert meta["outputs"]["actions"] == ["B", 8, 4] and meta["policy"]["chunk"]["action_offset"] == -1
    srv = PolicyServer(backend, ServerConfig(port=0, max_batch=1), log=lambda msg: None)
    srv.start_in_thread()
    try:
        client = PolicyClient(f"ws://127.0.0.1:{srv.port}")
        history = {"state": np.zeros((2, 7), np.float32)}  # obs_span = 2 frames of press_button's state
        reply = client.infer(history, seed=0, chunks=True)
        client.close()
    finally:
        srv.stop()
    assert reply["actions"].shape == (8, 4) and reply["chunks"].shape == (1, 16, 4)
    # DP's executed window: the chunk's actions 1..8 (action 0 is for the observed frame before the current one)
    np.testing.assert_allclose(reply["actions"], reply["chunks"][0, 1:9], atol=1e-6)
