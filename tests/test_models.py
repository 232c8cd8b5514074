"""Tests for the encoders, the HiPolicy U-Net (hierarchical FiLM, global fusion) and PolicyNet."""

from __future__ import annotations

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hipolicy_jax.config import PolicyConfig, replace
from hipolicy_jax.models import (
    ConditionalUnet1D,
    ImageEncoder,
    ObsEncoder,
    PolicyNet,
    SegmentFusion,
    crop_images,
    init_policy_params,
    init_variables,
    param_count,
)
from hipolicy_jax.models.unet import Conv1d, Upsample1d, apply_film

A = 4  # action dim
D = 10  # state dim
B = 2
LC = 8


def tiny_cfg(obs_type="state", strides=(1, 2, 3), **changes) -> PolicyConfig:
    base = {
        "chunk.strides": strides,
        "chunk.chunk_len": LC,
        "model.size": "tiny",
        "encoder.obs_type": obs_type,
        "encoder.state_hidden": (16,),
        "encoder.state_out": 8,
        "encoder.image_size": 32,
        "encoder.crop_size": 28,
        "encoder.image_channels": (8, 16),
        "encoder.num_keypoints": 4,
        "encoder.image_out": 8,
        "encoder.num_points": 64,
        "encoder.point_out": 8,
    }
    base.update(changes)
    return replace(PolicyConfig(), **base)


def make_obs(cfg: PolicyConfig, b=B, key=jax.random.key(0)):
    m, lh = cfg.chunk.num_freqs, cfg.chunk.obs_horizon
    k1, k2 = jax.random.split(key)
    obs = {"state": jax.random.normal(k1, (b, m, lh, D))}
    e = cfg.encoder
    if e.obs_type == "image":
        obs["image"] = jax.random.uniform(k2, (b, m, lh, e.image_size, e.image_size, 3), minval=-1.0, maxval=1.0)
    elif e.obs_type == "pointcloud":
        obs["point_cloud"] = jax.random.normal(k2, (b, m, lh, e.num_points, e.point_dims))
    return obs


def unet_for(cfg: PolicyConfig, **changes) -> ConditionalUnet1D:
    mc, ch = cfg.model, cfg.chunk
    kw = dict(down_dims=mc.unet_dims, kernel_size=mc.unet_kernel, n_groups=mc.n_groups,
              step_embed_dim=mc.unet_step_embed, num_freqs=ch.num_freqs, chunk_len=ch.chunk_len,
              condition=mc.condition, fusion=mc.fusion, fusion_heads=mc.fusion_heads)
    kw.update(changes)
    return ConditionalUnet1D(**kw)


def unet_inputs(m, b=B, dc=6, key=jax.random.key(1)):
    kx, kc = jax.random.split(key)
    x = jax.random.normal(kx, (b, m * LC, A))
    t = jnp.arange(b) * 7 + 3
    cond = jax.random.normal(kc, (b, m, dc))
    return x, t, cond


def paths(tree) -> set[str]:
    return {"/".join(str(getattr(k, "key", k)) for k in p) for p, _ in jax.tree_util.tree_leaves_with_path(tree)}


def shapes(tree):
    return jax.tree_util.tree_map(jnp.shape, tree)


@functools.partial(jax.jit, static_argnames=("net", "method"),
                   compiler_options={"xla_backend_optimization_level": 0})
def run(net: nn.Module, variables, *args, method: str = "__call__"):
    """Jitted ``net.apply``, compiled once per (module, method, shapes) without backend optimisation (fast to
    compile; these tiny models run in microseconds either way)."""
    return net.apply(variables, *args, method=method)


def quick_init(module: nn.Module, *args, seed: int = 0, **kwargs):
    """Variables with ``module.init``'s tree and shapes, filled from NumPy (fan-in scaled kernels, unit-ish norm
    scales, small biases). XLA compiles of random initialisers dominate these tests' run time on a CPU, and the
    behaviours tested here do not depend on the initialiser; ``init_policy_params`` itself is tested separately."""
    rng = np.random.default_rng(seed)

    def fill(path, leaf):
        name, parent = (str(getattr(k, "key", k)) for k in path[-1:-3:-1])
        if name == "scale":
            return jnp.asarray(1.0 + 0.1 * rng.standard_normal(leaf.shape), leaf.dtype)
        if name == "kernel":
            qkv = parent in ("query", "key", "value")  # attention kernels are (D, heads, head_dim)
            fan_in = leaf.shape[0] if qkv else int(np.prod(leaf.shape[:-1]))
            return jnp.asarray(rng.standard_normal(leaf.shape) / np.sqrt(fan_in), leaf.dtype)
        return jnp.asarray((1.0 if name == "cls" else 0.1) * rng.standard_normal(leaf.shape), leaf.dtype)  # bias, cls

    shapes_ = jax.eval_shape(lambda *a: module.init(jax.random.key(seed), *a, **kwargs), *args)
    return jax.tree_util.tree_map_with_path(fill, shapes_)


def differs(a, b, tol=1e-6) -> bool:
    return float(jnp.max(jnp.abs(a - b))) > tol


@pytest.fixture(scope="module")
def unet3():
    """Tiny M = 3 U-Net inputs and variables, with and without fusion: (cfg, (x, t, cond), {fusion: variables})."""
    cfg = tiny_cfg()
    inputs = unet_inputs(3)
    variables = {f: quick_init(unet_for(cfg, fusion=f), *inputs) for f in (True, False)}
    return cfg, inputs, variables


@pytest.fixture(scope="module")
def policy3():
    """Tiny M = 3 state-only PolicyNet: (cfg, obs, variables)."""
    cfg = tiny_cfg()
    obs = make_obs(cfg)
    return cfg, obs, init_policy_params(cfg, A, obs, jax.random.key(0))


# ----------------------------------------------------------------------------------------------------------- shapes


@pytest.mark.parametrize("obs_type", ["state", "image", "pointcloud"])
@pytest.mark.parametrize("strides", [(1,), (1, 2, 3)])
def test_policy_shapes(obs_type, strides):
    cfg = tiny_cfg(obs_type, strides)
    obs = make_obs(cfg)
    m, lh = len(strides), cfg.chunk.obs_horizon
    x = jax.random.normal(jax.random.key(2), (B, m * LC, A))
    t = jnp.array([0, 50])
    net = PolicyNet(cfg, A)
    variables = quick_init(net, obs, x, t)
    feat = {"state": 8, "image": 8 + 8, "pointcloud": 8 + 8}[obs_type]
    cond = run(net, variables, obs, method="encode")
    assert cond.shape == (B, m, lh * feat)
    out = run(net, variables, x, t, cond, method="denoise")
    assert out.shape == (B, m * LC, A)
    assert bool(jnp.all(jnp.isfinite(out)))


def test_init_policy_params(policy3):
    cfg, obs, variables = policy3
    net = PolicyNet(cfg, A)
    expected = jax.eval_shape(lambda: net.init(jax.random.key(0), obs, jnp.zeros((B, 3 * LC, A)), jnp.zeros((B,))))
    assert shapes(variables) == jax.tree_util.tree_map(lambda s: s.shape, expected)
    assert param_count(variables) == sum(p.size for p in jax.tree_util.tree_leaves(variables))
    assert param_count(variables) == param_count(variables["params"]["obs_encoder"]) + param_count(
        variables["params"]["unet"])
    assert all(bool(jnp.all(jnp.isfinite(p))) for p in jax.tree_util.tree_leaves(variables))
    cls = variables["params"]["unet"]["down0_res1"]["fusion"]["cls"]
    assert 0.5 < float(jnp.std(cls)) < 1.5  # learned CLS token drawn from N(0, 1)
    # the unoptimised-compile init draws the same values as a plain init
    fusion, x = SegmentFusion(num_segments=3), jnp.ones((1, 3 * LC, 2))
    fast, plain = init_variables(fusion, jax.random.key(3), x), fusion.init(jax.random.key(3), x)
    assert shapes(fast) == shapes(plain)
    for a, b in zip(jax.tree_util.tree_leaves(fast), jax.tree_util.tree_leaves(plain)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_encode_and_denoise_use_disjoint_params(policy3):
    cfg, obs, variables = policy3
    assert set(variables["params"]) == {"obs_encoder", "unet"}
    net = PolicyNet(cfg, A)
    enc_only = {"params": {"obs_encoder": variables["params"]["obs_encoder"]}}
    unet_only = {"params": {"unet": variables["params"]["unet"]}}
    cond = run(net, enc_only, obs, method="encode")
    x, t, _ = unet_inputs(3)
    out = run(net, unet_only, x, t, cond, method="denoise")
    np.testing.assert_allclose(out, run(net, variables, obs, x, t), rtol=1e-5, atol=1e-5)


def test_denoise_rejects_wrong_shapes(policy3):
    cfg, obs, variables = policy3
    net = PolicyNet(cfg, A)
    cond = run(net, variables, obs, method="encode")
    with pytest.raises(ValueError, match="x"):
        run(net, variables, jnp.zeros((B, 2 * LC, A)), jnp.zeros((B,)), cond, method="denoise")
    with pytest.raises(ValueError, match="action_dim"):
        run(net, variables, jnp.zeros((B, 3 * LC, A + 1)), jnp.zeros((B,)), cond, method="denoise")
    with pytest.raises(ValueError, match="cond"):
        run(net, variables, jnp.zeros((B, 3 * LC, A)), jnp.zeros((B,)), cond[:, :2], method="denoise")


# ---------------------------------------------------------------------------------------------- fusion parameters


def test_single_frequency_is_plain_diffusion_policy_unet():
    cfg = tiny_cfg(strides=(1,))
    x, t, cond = unet_inputs(1)
    with_fusion = quick_init(unet_for(cfg, fusion=True), x, t, cond)
    without = jax.eval_shape(unet_for(cfg, fusion=False).init, jax.random.key(0), x, t, cond)
    assert not any("fusion" in p or "cls" in p for p in paths(with_fusion))
    assert shapes(with_fusion) == jax.tree_util.tree_map(lambda s: s.shape, without)
    out_f = run(unet_for(cfg, fusion=True), with_fusion, x, t, cond)
    np.testing.assert_array_equal(out_f, run(unet_for(cfg, fusion=False), with_fusion, x, t, cond))
    # One FiLM condition for the whole sequence: every condition mode is the same network at M = 1.
    for mode in ("low", "high"):
        np.testing.assert_array_equal(out_f, run(unet_for(cfg, condition=mode), with_fusion, x, t, cond))
    # A scalar timestep broadcasts over the batch.
    same_t = run(unet_for(cfg), with_fusion, x, jnp.full((B,), 5), cond)
    np.testing.assert_allclose(run(unet_for(cfg), with_fusion, x, 5, cond), same_t, rtol=1e-6, atol=1e-6)


def test_fusion_parameters_at_three_frequencies(unet3):
    cfg, _, variables = unet3
    c0 = cfg.model.unet_dims[0]
    params = variables[True]["params"]
    fused = {p.split("/")[0] for p in paths(params) if "/fusion/" in p}
    assert fused == {"down0_res0", "down0_res1"}  # both blocks of the first down level, as in the release
    # first block: tokens are raw action segments (A * L_c); second: down_dims[0] features (C * L_c)
    assert params["down0_res0"]["fusion"]["cls"].shape == (1, 1, A * LC)
    assert params["down0_res1"]["fusion"]["cls"].shape == (1, 1, c0 * LC)
    # the first conv sees [x, global] (2 C_in) and emits [local, global] (2 C); the second maps 2 C -> C
    assert params["down0_res1"]["block0"]["conv"]["kernel"].shape == (cfg.model.unet_kernel, 2 * c0, 2 * c0)
    assert params["down0_res1"]["block1"]["conv"]["kernel"].shape == (cfg.model.unet_kernel, 2 * c0, c0)
    no_fusion = variables[False]["params"]
    assert not any("fusion" in p for p in paths(no_fusion))
    assert param_count(params) > param_count(no_fusion)


# --------------------------------------------------------------------------------------------------- ablations


def test_condition_modes_and_fusion_change_the_output(unet3):
    cfg, (x, t, cond), all_variables = unet3
    variables = all_variables[True]
    outs = {mode: run(unet_for(cfg, condition=mode), variables, x, t, cond) for mode in ("hier", "low", "high")}
    assert differs(outs["hier"], outs["low"])
    assert differs(outs["hier"], outs["high"])
    assert differs(outs["low"], outs["high"])
    # fusion on vs off (different parameter trees, same init key)
    assert differs(outs["hier"], run(unet_for(cfg, fusion=False), all_variables[False], x, t, cond))
    # with the same params, the learned CLS token feeds the output
    bumped = jax.tree_util.tree_map(lambda a: a, variables)
    bumped["params"]["down0_res1"]["fusion"]["cls"] = bumped["params"]["down0_res1"]["fusion"]["cls"] + 1.0
    assert differs(outs["hier"], run(unet_for(cfg), bumped, x, t, cond))


@pytest.mark.parametrize("t", [1, 2, 4, 5, 9])
@pytest.mark.parametrize("kernel_size,stride", [(5, 1), (3, 2), (1, 1)])
def test_conv1d_matches_nn_conv(t, kernel_size, stride):
    """Same parameter tree and init as ``nn.Conv``, same outputs and gradients, also where ``T < k`` (im2col path)."""
    x = jax.random.normal(jax.random.key(0), (3, t, 6))
    ref = nn.Conv(7, (kernel_size,), strides=stride, padding=kernel_size // 2)
    ours = Conv1d(7, kernel_size, stride=stride)
    p_ref, p_ours = ref.init(jax.random.key(1), x), ours.init(jax.random.key(1), x)
    assert jax.tree.all(jax.tree.map(lambda a, b: a.shape == b.shape and bool(jnp.all(a == b)), p_ref, p_ours))
    p = jax.tree.map(lambda a: a + jax.random.normal(jax.random.key(2), a.shape), p_ref)  # non-zero bias
    np.testing.assert_allclose(ours.apply(p, x), ref.apply(p, x), atol=1e-5)
    g_ref = jax.grad(lambda p, x: jnp.sum(jnp.sin(ref.apply(p, x))), argnums=(0, 1))(p, x)
    g_ours = jax.grad(lambda p, x: jnp.sum(jnp.sin(ours.apply(p, x))), argnums=(0, 1))(p, x)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, atol=1e-4), g_ours, g_ref)


@pytest.mark.parametrize("t", [1, 2, 4, 7])
def test_upsample_matches_conv_transpose(t):
    """``Upsample1d`` is ``nn.ConvTranspose(C, (4,), strides=(2,), padding=((2, 2),))``: params, init and outputs."""
    x = jax.random.normal(jax.random.key(0), (2, t, 5))
    ref = nn.ConvTranspose(3, (4,), strides=(2,), padding=((2, 2),))
    ours = Upsample1d(3)
    p_ref, p_ours = ref.init(jax.random.key(1), x), ours.init(jax.random.key(1), x)
    assert jax.tree.all(jax.tree.map(lambda a, b: a.shape == b.shape and bool(jnp.all(a == b)), p_ref, p_ours))
    p = jax.tree.map(lambda a: a + jax.random.normal(jax.random.key(2), a.shape), p_ref)
    y = ours.apply(p, x)
    assert y.shape == (2, 2 * t, 3)
    np.testing.assert_allclose(y, ref.apply(p, x), atol=1e-5)


def test_apply_film_modulates_each_segment_with_its_own_condition():
    x = jax.random.normal(jax.random.key(0), (2, 12, 5))
    embed = jax.random.normal(jax.random.key(1), (2, 3, 10))
    y = apply_film(x, embed)
    for k in range(3):
        seg = slice(4 * k, 4 * (k + 1))
        expected = x[:, seg] * embed[:, k, None, :5] + embed[:, k, None, 5:]
        np.testing.assert_allclose(y[:, seg], expected, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("fusion", [True, False])
def test_hierarchical_film_is_per_segment(unet3, fusion):
    cfg, (x, t, cond), all_variables = unet3
    variables = all_variables[fusion]
    nets = {mode: unet_for(cfg, fusion=fusion, condition=mode) for mode in ("hier", "low", "high")}
    base = {mode: run(n, variables, x, t, cond) for mode, n in nets.items()}
    for m in range(3):
        c2 = cond.at[:, m].add(1.0)
        assert differs(run(nets["hier"], variables, x, t, c2), base["hier"]), f"hier ignores cond[:, {m}]"
        low = run(nets["low"], variables, x, t, c2)
        high = run(nets["high"], variables, x, t, c2)
        if m == 0:
            assert differs(low, base["low"])
            np.testing.assert_array_equal(high, base["high"])
        elif m == 2:
            np.testing.assert_array_equal(low, base["low"])
            assert differs(high, base["high"])
        else:
            np.testing.assert_array_equal(low, base["low"])
            np.testing.assert_array_equal(high, base["high"])


# ------------------------------------------------------------------------------------------------------- fusion


def test_segment_fusion_mixes_tokens_within_each_sample_only():
    x = jax.random.normal(jax.random.key(0), (3, 3 * LC, 4))
    fusion = SegmentFusion(num_segments=3, num_heads=8)
    variables = quick_init(fusion, x)
    base = fusion.apply(variables, x)
    assert base.shape == (3, LC, 4)
    assert differs(base[0], base[1])  # the global feature depends on the sample (the release's does not)
    for m in range(3):
        y = fusion.apply(variables, x.at[1, m * LC:(m + 1) * LC].add(1.0))
        assert differs(y[1], base[1]), f"global feature ignores segment {m}"
        np.testing.assert_array_equal(y[0], base[0])
        np.testing.assert_array_equal(y[2], base[2])


def test_unet_has_no_cross_batch_leakage(unet3):
    cfg, _, all_variables = unet3
    x, t, cond = unet_inputs(3, b=3)
    net = unet_for(cfg)
    variables = all_variables[True]
    base = run(net, variables, x, t, cond)
    out = run(net, variables, x.at[1].add(1.0), t, cond.at[1].add(1.0))
    assert differs(out[1], base[1])
    np.testing.assert_allclose(out[0], base[0], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(out[2], base[2], rtol=1e-6, atol=1e-6)
    singles = jnp.concatenate([run(net, variables, x[i:i + 1], t[i:i + 1], cond[i:i + 1]) for i in range(3)])
    np.testing.assert_allclose(singles, base, rtol=1e-5, atol=1e-5)


def test_fusion_path_carries_one_segment_to_the_others(unet3):
    """Perturb segment 0 of sample 1; compare against the same run with every fusion output frozen at its
    unperturbed value. The difference, in segment M-1 of sample 1, is what flowed through the fusion path."""
    cfg, (x, t, cond), all_variables = unet3
    net = unet_for(cfg)
    variables = all_variables[True]
    recorded = []

    def record(next_fun, args, kwargs, context):
        out = next_fun(*args, **kwargs)
        if isinstance(context.module, SegmentFusion) and context.method_name == "__call__":
            recorded.append(out)
        return out

    with nn.intercept_methods(record):
        net.apply(variables, x, t, cond)  # eager: interceptors act at trace time, a jit cache would skip them
    assert len(recorded) == 2
    frozen = iter(recorded)

    def freeze(next_fun, args, kwargs, context):
        if isinstance(context.module, SegmentFusion) and context.method_name == "__call__":
            return next(frozen)
        return next_fun(*args, **kwargs)

    x2 = x.at[1, :LC].add(1.0)
    live = net.apply(variables, x2, t, cond)
    with nn.intercept_methods(freeze):
        blocked = net.apply(variables, x2, t, cond)
    last = slice(2 * LC, 3 * LC)
    assert differs(live[1, last], blocked[1, last])
    np.testing.assert_allclose(live[0], blocked[0], rtol=1e-6, atol=1e-6)  # sample 0's fusion input is unchanged


# ------------------------------------------------------------------------------------------------------ encoders


def test_random_crop_per_image_and_deterministic_centre_crop():
    h = 12
    grid = jnp.arange(h * h, dtype=jnp.float32).reshape(1, h, h, 1)
    images = jnp.tile(grid, (16, 1, 1, 3))
    a = crop_images(images, 8, jax.random.key(0))
    b = crop_images(images, 8, jax.random.key(1))
    assert a.shape == (16, 8, 8, 3)
    assert differs(a, b)
    np.testing.assert_array_equal(a, crop_images(images, 8, jax.random.key(0)))
    assert len({float(v) for v in a[:, 0, 0, 0]}) > 1  # identical images got different offsets
    centre = crop_images(images, 8, None)
    np.testing.assert_array_equal(centre, images[:, 2:10, 2:10])
    np.testing.assert_array_equal(centre, crop_images(images, 8, None))


def test_image_encoder_train_crops_depend_on_rng():
    enc = ImageEncoder(channels=(8, 16), num_keypoints=4, out_dim=6, crop_size=28)
    imgs = jax.random.uniform(jax.random.key(0), (2, 3, 32, 32, 3), minval=-1.0, maxval=1.0)
    variables = quick_init(enc, imgs)
    evals = [enc.apply(variables, imgs) for _ in range(2)]
    assert evals[0].shape == (2, 3, 6)
    np.testing.assert_array_equal(evals[0], evals[1])
    t0 = enc.apply(variables, imgs, train=True, rngs={"crop": jax.random.key(2)})
    t1 = enc.apply(variables, imgs, train=True, rngs={"crop": jax.random.key(3)})
    assert differs(t0, t1)
    assert differs(t0, evals[0])


def test_obs_encoder_shares_weights_across_frames_and_frequencies():
    cfg = tiny_cfg("pointcloud")
    obs = make_obs(cfg)
    enc = ObsEncoder(cfg.encoder)
    variables = quick_init(enc, obs)
    cond = enc.apply(variables, obs)
    # swapping two frequencies' windows swaps their conditions
    swapped = {k: v[:, ::-1] for k, v in obs.items()}
    np.testing.assert_allclose(enc.apply(variables, swapped), cond[:, ::-1], rtol=1e-5, atol=1e-5)
    # the condition of frequency m is its L_h frame features, flattened in frame order
    one_frame = {k: v[:, :, 1:2] for k, v in obs.items()}
    f = cond.shape[-1] // cfg.chunk.obs_horizon
    np.testing.assert_allclose(enc.apply(variables, one_frame), cond[:, :, f:2 * f], rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("obs_type", ["pointcloud", "image"])
def test_obs_encoder_encodes_each_distinct_frame_once(obs_type):
    """With the windows' frame offsets the encoder runs on the 6 distinct steps of strides 1/2/3 x L_h 3 (not 9)
    and gives the per-position result on windows gathered from one frame sequence (as ``data.windowing`` does)."""
    from hipolicy_jax.data.windowing import history_window_indices, obs_offsets
    from hipolicy_jax.models.encoders import ImageEncoder, PointCloudEncoder

    cfg = tiny_cfg(obs_type)
    span, idx = cfg.chunk.obs_span, history_window_indices(cfg.chunk)  # (M, L_h) into the span frames
    seq = {k: jax.random.normal(jax.random.key(i), (B, span) + v.shape[3:])
           for i, (k, v) in enumerate(make_obs(cfg).items())}
    obs = {k: v[:, idx] for k, v in seq.items()}  # (B, M, L_h, ...): equal offsets hold equal frames
    offsets = tuple(map(tuple, obs_offsets(cfg.chunk).tolist()))
    plain, shared = ObsEncoder(cfg.encoder), ObsEncoder(cfg.encoder, frame_offsets=offsets)
    variables = quick_init(plain, obs)
    heavy = ImageEncoder if obs_type == "image" else PointCloudEncoder
    seen = []

    def record(next_fun, args, kwargs, context):
        if isinstance(context.module, heavy) and context.method_name == "__call__":
            seen.append(args[0].shape[:2])
        return next_fun(*args, **kwargs)

    with nn.intercept_methods(record):
        out = shared.apply(variables, obs)
    assert seen == [(B, len(np.unique(obs_offsets(cfg.chunk))))] == [(B, 6)]
    np.testing.assert_allclose(out, plain.apply(variables, obs), rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="frame_offsets"):
        ObsEncoder(cfg.encoder, frame_offsets=offsets[:2]).apply(variables, obs)


def test_obs_encoder_state_dims_reads_only_leading_features():
    """``encoder.state_dims = k``: the state MLP's kernel has k inputs and the features beyond k change nothing (a
    point-cloud policy sees objects only through the camera); a state with fewer than k features is rejected."""
    cfg = tiny_cfg("pointcloud", **{"encoder.state_dims": 4})
    obs = make_obs(cfg)
    enc = ObsEncoder(cfg.encoder)
    variables = quick_init(enc, obs)
    assert variables["params"]["state"]["dense_0"]["kernel"].shape[0] == 4
    moved = dict(obs, state=obs["state"].at[..., 4:].add(3.0))
    np.testing.assert_array_equal(enc.apply(variables, moved), enc.apply(variables, obs))
    touched = dict(obs, state=obs["state"].at[..., 3].add(3.0))
    assert not np.allclose(enc.apply(variables, touched), enc.apply(variables, obs))
    with pytest.raises(ValueError, match=r"encoder.state_dims=4 .*D=3"):
        enc.apply(variables, dict(obs, state=obs["state"][..., :3]))
    with pytest.raises(ValueError, match="encoder.state_dims"):
        tiny_cfg(**{"encoder.state_dims": 0})


@pytest.mark.parametrize(
    "obs_type, key, bad",
    [
        ("state", "state", None),
        ("state", "state", (B, 3, 3, D, 1)),
        ("image", "image", None),
        ("image", "image", (B, 3, 3, 32, 32)),
        ("image", "image", (B, 3, 3, 30, 30, 3)),
        ("pointcloud", "point_cloud", None),
        ("pointcloud", "point_cloud", (B, 3, 64, 3)),
        ("pointcloud", "point_cloud", (B, 3, 3, 64, 6)),
        ("pointcloud", "point_cloud", (B + 1, 3, 3, 64, 3)),
    ],
)
def test_obs_encoder_rejects_bad_observations(obs_type, key, bad):
    cfg = tiny_cfg(obs_type)
    obs = make_obs(cfg)
    if bad is None:
        del obs[key]
    else:
        obs[key] = jnp.zeros(bad)
    with pytest.raises(ValueError, match=f"obs\\['{key}'\\]"):
        ObsEncoder(cfg.encoder).init(jax.random.key(0), obs)


def test_one_stride_with_the_identity_state_encoder_is_diffusion_policy_lowdim_to_the_parameter():
    """Diffusion Policy's low-dim U-Net (down dims 256/512/1024, kernel 5, step embedding 256, the raw 2 x 20 obs
    window as the condition, A = 2, horizon 16) has 65,783,298 parameters; so has one stride here."""
    from hipolicy_jax.config import ChunkConfig, EncoderConfig, ModelConfig, PolicyConfig
    from hipolicy_jax.models.policy_net import init_policy_params, param_count

    cfg = PolicyConfig(chunk=ChunkConfig(strides=(1,), obs_horizon=2, chunk_len=16),
                       encoder=EncoderConfig(state_encoder="identity"),
                       model=ModelConfig(size="paper", step_embed_dim=256))
    obs = {"state": jnp.zeros((1, 1, 2, 20))}
    shapes = jax.eval_shape(lambda: init_policy_params(cfg, 2, obs, jax.random.key(0)))
    assert param_count(shapes) == 65_783_298
    assert "obs_encoder" not in shapes["params"]  # nothing between the observations and the FiLM heads


@pytest.mark.parametrize("t", [2, 4, 9])
@pytest.mark.parametrize("kernel_size,stride", [(5, 1), (3, 2), (1, 1)])
def test_conv1d_bfloat16_is_a_float32_output_close_to_float32(t, kernel_size, stride):
    """``compute_dtype='bfloat16'``: bf16 operands, float32 output and gradients within bf16 rounding (~2^-8
    relative) of the float32 convolution, on the same parameter tree."""
    x = jax.random.normal(jax.random.key(0), (3, t, 64))
    f32, bf16 = Conv1d(32, kernel_size, stride=stride), Conv1d(32, kernel_size, stride=stride, compute_dtype="bfloat16")
    p = f32.init(jax.random.key(1), x)
    assert jax.tree.structure(p) == jax.tree.structure(bf16.init(jax.random.key(1), x))
    y32, y16 = f32.apply(p, x), bf16.apply(p, x)
    assert y16.dtype == jnp.float32 and y16.shape == y32.shape
    rel = float(jnp.linalg.norm(y16 - y32) / jnp.linalg.norm(y32))
    assert 1e-5 < rel < 1e-2, rel  # really bf16 (not silently float32), and close
    g32 = jax.grad(lambda p: jnp.sum(jnp.sin(f32.apply(p, x))))(p)
    g16 = jax.grad(lambda p: jnp.sum(jnp.sin(bf16.apply(p, x))))(p)
    for a, b in zip(jax.tree.leaves(g16), jax.tree.leaves(g32)):
        assert a.dtype == jnp.float32
        assert float(jnp.linalg.norm(a - b) / jnp.linalg.norm(b)) < 2e-2


@pytest.mark.parametrize("fusion", [True, False])
def test_unet_bfloat16_same_parameters_close_outputs(fusion):
    """The bf16 U-Net has the float32 one's parameter tree (same init); its output is float32 and within 2 % (relative
    L2) of the float32 output on the same parameters; the float32 path is untouched by the option."""
    kw = dict(down_dims=(32, 64, 128), step_embed_dim=16, num_freqs=3, chunk_len=8, fusion=fusion, fusion_heads=4)
    x = jax.random.normal(jax.random.key(0), (4, 24, A))
    t = jnp.array([0, 10, 50, 99])
    cond = jax.random.normal(jax.random.key(1), (4, 3, 12))
    f32, bf16 = ConditionalUnet1D(**kw), ConditionalUnet1D(**kw, compute_dtype="bfloat16")
    p = f32.init(jax.random.key(2), x, t, cond)
    p16 = bf16.init(jax.random.key(2), x, t, cond)
    jax.tree.map(np.testing.assert_array_equal, p, p16)
    y32, y16 = f32.apply(p, x, t, cond), bf16.apply(p, x, t, cond)
    assert y16.dtype == jnp.float32
    rel = float(jnp.linalg.norm(y16 - y32) / jnp.linalg.norm(y32))
    assert 1e-5 < rel < 2e-2, rel


def test_compute_dtype_is_validated():
    with pytest.raises(ValueError, match="model.compute_dtype"):
        replace(PolicyConfig(), **{"model.compute_dtype": "float16"})


def test_light_fusion_projects_wide_tokens_only():
    """``fusion_token_dim``: segment tokens wider than it are projected before the attention (fewer parameters, the
    same output shape, the CLS token still feeds the output); narrower tokens keep the paper's form."""
    x = jax.random.normal(jax.random.key(0), (2, 3 * 8, 32))  # L*C = 256
    paper, light = SegmentFusion(3, 4), SegmentFusion(3, 4, token_dim=64)
    p_paper, p_light = paper.init(jax.random.key(1), x), light.init(jax.random.key(1), x)
    assert set(p_light["params"]) == {"cls", "token_in", "attention", "token_out"}
    assert p_light["params"]["cls"].shape == (1, 1, 64)
    assert param_count(p_light) < param_count(p_paper) / 3
    y = light.apply(p_light, x)
    assert y.shape == (2, 8, 32) and bool(jnp.all(jnp.isfinite(y)))
    bumped = jax.tree.map(lambda a: a, p_light)
    bumped["params"]["cls"] = bumped["params"]["cls"] + 1.0
    assert float(jnp.abs(light.apply(bumped, x) - y).max()) > 1e-4
    narrow = jax.random.normal(jax.random.key(0), (2, 3 * 8, 4))  # L*C = 32 <= 64: the paper's form
    assert set(SegmentFusion(3, 4, token_dim=64).init(jax.random.key(1), narrow)["params"]) == {"cls", "attention"}


def test_lowp_kernels_casts_conv_and_attention_kernels_only():
    """The sampler's once-per-call cast: conv and fusion-attention kernels to bf16, FiLM / step MLP / norms / biases
    stay float32, and the bf16 U-Net gives the same output on the cast tree (it casts those kernels itself)."""
    from hipolicy_jax.models.unet import lowp_kernels

    kw = dict(down_dims=(32, 64), step_embed_dim=16, num_freqs=2, chunk_len=4, fusion_heads=2,
              compute_dtype="bfloat16")
    x, t, cond = jnp.ones((2, 8, A)), jnp.array([1, 7]), jnp.ones((2, 2, 6))
    net = ConditionalUnet1D(**kw)
    p = net.init(jax.random.key(0), x, t, cond)
    low = lowp_kernels(p, "bfloat16")
    flat = {jax.tree_util.keystr(k): v for k, v in jax.tree_util.tree_flatten_with_path(low)[0]}
    cast = {k for k, v in flat.items() if v.dtype == jnp.bfloat16}
    assert any("conv" in k for k in cast) and any("attention" in k for k in cast)
    assert any("upsample" in k for k in cast) and any("final_conv" in k for k in cast)
    assert not any(s in k for k in cast for s in ("film", "step_dense", "norm", "bias", "cls"))
    assert lowp_kernels(p, "float32") is p
    np.testing.assert_allclose(net.apply(low, x, t, cond), net.apply(p, x, t, cond), atol=1e-6)
