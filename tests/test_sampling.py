"""The one-call sampler: entropy closed forms, threshold table, segment selection, determinism, no retrace.

A fake network with the ``PolicyNet`` protocol (``apply(params, ..., method=encode|denoise)``) keeps these tests
exact; tests with the real network live in test_policy.py.
"""

import functools
import math

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hipolicy_jax.config import ChunkConfig, DiffusionConfig, InferenceConfig, PolicyConfig
from hipolicy_jax.sampling import action_entropy, make_sampler, sample, segment_of, select_frequency


def test_entropy_two_samples_exact():
    a = jnp.array([[[0.0, 1.0]], [[0.2, 0.4]]])  # (N=2, T=1, A=2)
    var = np.array([0.02, 0.18])  # (a-b)²/2, ddof=1
    expected = np.mean(0.5 * np.log(2 * np.pi * np.e * var + 1e-6))
    assert float(action_entropy(a)) == pytest.approx(expected, rel=1e-5)


def test_entropy_of_gaussian_samples_matches_closed_form():
    sigma = jnp.array([0.05, 0.3])
    x = jax.random.normal(jax.random.key(0), (2, 4000, 6, 3)) * sigma[:, None, None, None]
    h = np.asarray(action_entropy(x))
    np.testing.assert_allclose(h, 0.5 * np.log(2 * np.pi * np.e * np.asarray(sigma) ** 2), atol=0.02)


RELEASE = (-math.inf, -6.0, -5.5, math.inf)


@pytest.mark.parametrize("h,expected", [(-7.0, 0), (-6.0001, 0), (-6.0, 1), (-5.75, 1), (-5.5, 2), (3.0, 2),
                                        (float("nan"), 0)])
def test_release_threshold_table(h, expected):
    """Release: H < -6 → short (stride 1), H < -5.5 → mid, else long; lowest entropy → highest frequency."""
    assert int(select_frequency(jnp.float32(h), RELEASE, 3)) == expected


def test_finite_outer_thresholds_clamp_and_none_means_highest_frequency():
    th = (-8.0, -6.0, -5.5, -5.0)
    got = select_frequency(jnp.array([-9.0, -7.0, -5.7, -5.2, -4.0]), th, 3)
    np.testing.assert_array_equal(np.asarray(got), [0, 0, 1, 2, 2])
    np.testing.assert_array_equal(np.asarray(select_frequency(jnp.array([-9.0, 9.0]), None, 3)), [0, 0])
    np.testing.assert_array_equal(np.asarray(select_frequency(jnp.array([-9.0, 9.0]), (0.0, 1.0), 1)), [0, 0])


def test_segment_of_picks_the_selected_stride():
    chunk = ChunkConfig(strides=(1, 2, 3), chunk_len=4)
    # segments in descending-stride order: stride 3 | stride 2 | stride 1, filled with their stride
    chunks = jnp.concatenate([jnp.full((2, 4, 1), s, jnp.float32) for s in chunk.segment_strides], axis=1)
    out = segment_of(chunk, chunks, jnp.array([0, 2]))
    assert out.shape == (2, 4, 1)
    np.testing.assert_array_equal(np.asarray(out[:, 0, 0]), [1.0, 3.0])


def test_calibrate_thresholds_are_the_percentiles_of_the_finite_entropies():
    """``calibrate_thresholds`` = (−inf, np.percentile(finite entropies, p)..., +inf), by value: the paper's (10, 70)
    for M = 3 (by hand on 1..5: linear interpolation at positions 0.4 and 2.8 → 1.4, 3.8), given percentiles, the
    evenly spaced default for M = 4; NaN / ±inf entropies (N = 1 draws, overflow) are left out; ties stay strictly
    ascending (+1e-9 per inner threshold); one frequency has nothing to select."""
    from hipolicy_jax.evaluation.calibration import calibrate_thresholds
    th = calibrate_thresholds(np.array([5.0, 1.0, np.nan, 4.0, 2.0, 3.0, -np.inf]), 3)
    assert th[0] == -math.inf and th[-1] == math.inf and len(th) == 4
    np.testing.assert_allclose(th[1:3], [1.4, 3.8], rtol=0, atol=1e-8)
    h = np.random.default_rng(0).normal(-5.0, 0.7, size=(7, 9))  # any shape: flattened
    for m, p, want_p in [(3, None, (10, 70)), (3, (20, 80), (20, 80)), (4, None, (25, 50, 75)),
                         (4, (5, 50, 95), (5, 50, 95))]:
        th = calibrate_thresholds(h, m, p)
        assert len(th) == m + 1 and th[0] == -math.inf and th[-1] == math.inf
        np.testing.assert_allclose(th[1:-1], np.percentile(h.ravel(), want_p), rtol=0, atol=1e-8)
    tied = calibrate_thresholds(np.full(10, -6.0), 3)
    assert tied[1] == pytest.approx(-6.0, abs=1e-8) and tied[1] < tied[2] == pytest.approx(-6.0, abs=1e-8)
    assert calibrate_thresholds(h, 1) == (-math.inf, math.inf)
    with pytest.raises(ValueError, match="no finite entropies"):
        calibrate_thresholds(np.array([np.nan, np.nan]), 3)


# --------------------------------------------------------------------------------------------- fake network
class FakeNet:
    """encode: mean over the obs window; denoise: x0 = tanh(w·cond mean) + v·x_t (sample-prediction)."""

    def __init__(self):
        self.traces = 0

    def encode(self, obs, train=False):  # protocol marker only
        raise AssertionError

    def denoise(self, x, t, cond):  # protocol marker only
        raise AssertionError

    def apply(self, params, *args, method, **kw):
        self.traces += 1
        if method == self.encode:
            return args[0]["state"].mean(axis=2)  # (B, M, D)
        x, t, cond = args
        target = jnp.tanh(params["w"] * cond.mean(axis=(1, 2)))[:, None, None]
        return target + params["v"] * x


@flax.struct.dataclass
class AffineNormalizer:
    scale: jax.Array

    def normalize_obs(self, obs):
        return obs

    def unnormalize(self, key, x):
        assert key == "action"
        return x * self.scale

    def normalize(self, key, x):
        assert key == "action"
        return x / self.scale


def _cfg(strides=(1, 2, 3), steps=10, objective="diffusion"):
    return PolicyConfig(chunk=ChunkConfig(strides=strides, chunk_len=4), objective=objective,
                        diffusion=DiffusionConfig(prediction_type="sample", num_train_steps=steps))


def _sampler(net, n, steps=10, objective="diffusion", sampler="ddpm"):
    """A compiled sampler of the fake network: every DDPM step (diffusion) or ``steps`` Euler steps (flow)."""
    inference = InferenceConfig(num_samples=n, sampler=sampler if objective == "diffusion" else "euler",
                                num_steps=steps)
    return make_sampler(net, _cfg(steps=steps, objective=objective), 2, inference)


def _obs(b=2, m=3):
    return {"state": jnp.arange(b * m * 3 * 5, dtype=jnp.float32).reshape(b, m, 3, 5) / 100.0}


def test_sampler_shapes_and_collapsed_samples_give_closed_form_entropy():
    net = FakeNet()
    fn = _sampler(net, 8)
    params = {"w": jnp.float32(1.0), "v": jnp.float32(0.0)}  # x0 independent of noise → all samples equal
    res = fn(params, AffineNormalizer(jnp.float32(2.0)), _obs(), jax.random.key(0), RELEASE)
    assert res.chunks.shape == (2, 8, 12, 2) and res.actions.shape == (2, 4, 2)
    target = 2.0 * np.tanh(np.asarray(_obs()["state"]).mean(axis=(1, 2, 3)))
    np.testing.assert_allclose(np.asarray(res.chunks[:, :, 0, 0]), np.repeat(target[:, None], 8, 1), rtol=1e-5)
    h0 = 0.5 * math.log(1e-6)  # var = 0 → 0.5·log(2πe·0 + ε) ≈ -6.91
    np.testing.assert_allclose(np.asarray(res.entropy), [h0, h0], rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(res.stride), [1, 1])  # -6.91 < -6 → short (stride 1)
    res2 = fn(params, AffineNormalizer(jnp.float32(2.0)), _obs(), jax.random.key(0),
              jnp.array([-jnp.inf, -8.0, -7.0, jnp.inf]))
    np.testing.assert_array_equal(np.asarray(res2.stride), [3, 3])  # same entropy, lower thresholds → long


@pytest.mark.parametrize("objective", ["diffusion", "flow"])
def test_sampler_deterministic_per_key_different_across_keys_and_no_retrace(objective):
    net = FakeNet()
    fn = _sampler(net, 5, objective=objective)
    params = {"w": jnp.float32(0.5), "v": jnp.float32(0.3)}
    norm = AffineNormalizer(jnp.float32(1.0))
    a = fn(params, norm, _obs(), jax.random.key(1))
    traces = net.traces
    assert traces > 0
    b = fn(params, norm, _obs(), jax.random.key(1))
    c = fn(params, norm, _obs(), jax.random.key(2))
    d = fn({"w": jnp.float32(0.7), "v": jnp.float32(0.3)}, norm, _obs(), jax.random.key(2))
    assert net.traces == traces and fn._cache_size() == 1, "equal shapes must not retrace"
    np.testing.assert_array_equal(np.asarray(a.chunks), np.asarray(b.chunks))
    assert not np.allclose(np.asarray(a.chunks), np.asarray(c.chunks))
    assert not np.allclose(np.asarray(c.chunks), np.asarray(d.chunks))
    # samples within one call differ (independent noise per sample)
    assert np.all(np.asarray(a.chunks).std(axis=1) > 0)
    assert np.all(np.isfinite(np.asarray(a.entropy)))


def test_single_sample_skips_entropy_and_runs_highest_frequency():
    fn = _sampler(FakeNet(), 1)
    res = fn({"w": jnp.float32(0.5), "v": jnp.float32(0.3)}, AffineNormalizer(jnp.float32(1.0)), _obs(),
             jax.random.key(0), RELEASE)
    assert res.chunks.shape == (2, 1, 12, 2)
    assert np.all(np.isnan(np.asarray(res.entropy)))
    np.testing.assert_array_equal(np.asarray(res.stride), [1, 1])
    np.testing.assert_array_equal(np.asarray(res.actions), np.asarray(res.chunks[:, 0, 8:12]))


@pytest.mark.parametrize("execution,drawn", [("chunk", 1), ("te", 1), ("aac", 16)])
def test_single_frequency_decision_draws_sample_zero_alone(execution, drawn):
    """Plain Diffusion Policy (one stride) executes sample 0 and, without AAC, reads no entropy: a decision draws
    sample 0 alone. Its key is ``split(key, N)[0]``, the key an N = 1 draw uses, so it executes the chunk the N = 16
    draw would have (to float rounding), at 1/16 of the sampler's cost; several strides always draw N."""
    from hipolicy_jax.evaluation.policy import PolicyArgs, make_decision_fn
    inference = InferenceConfig(num_samples=16, sampler="ddpm", num_steps=10, execution=execution)
    assert inference.samples_drawn(1) == drawn and inference.samples_drawn(3) == 16
    assert inference.decision_settings(1).num_samples == drawn and inference.decision_settings(1).execution == execution
    key = jax.random.key(5)
    np.testing.assert_array_equal(jax.random.key_data(jax.random.split(key, 16)[0]),
                                  jax.random.key_data(jax.random.split(key, 1)[0]))
    cfg, net = _cfg(strides=(1,)), FakeNet()
    args = PolicyArgs({"w": jnp.float32(0.5), "v": jnp.float32(0.3)}, AffineNormalizer(jnp.float32(2.0)))
    history = {"state": jnp.arange(cfg.chunk.obs_span * 5, dtype=jnp.float32).reshape(cfg.chunk.obs_span, 5) / 50}
    decision = make_decision_fn(net, cfg, 2, inference)(history, key, args)
    # the reference is the other draw: N = 16 (AAC) for a decision that draws sample 0 alone, N = 1 (whole chunks)
    # for AAC's N = 16 decision; sample 0 is the same either way
    other = "aac" if drawn == 1 else "chunk"
    reference = make_decision_fn(net, cfg, 2, InferenceConfig(num_samples=16, sampler="ddpm", num_steps=10,
                                                              execution=other))(history, key, args)
    assert decision.chunks.shape == (drawn, 4, 2) and reference.chunks.shape == (17 - drawn, 4, 2)
    np.testing.assert_allclose(np.asarray(decision.actions), np.asarray(reference.actions), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(np.asarray(decision.chunks[0]), np.asarray(reference.chunks[0]), rtol=1e-6, atol=1e-6)
    many = decision if drawn == 16 else reference
    assert np.all(np.asarray(many.chunks).std(axis=0) > 1e-3)  # N = 16 different samples, not one repeated
    assert np.isnan(float(decision.entropy)) == (drawn == 1)
    assert np.isnan(float(reference.entropy)) == (drawn == 16)
    several = make_decision_fn(net, _cfg(), 2, inference)(
        {"state": jnp.zeros((_cfg().chunk.obs_span, 5))}, key, args)
    assert several.chunks.shape[0] == 16


@pytest.mark.parametrize("objective,sampler,steps", [("diffusion", "ddpm", 10), ("diffusion", "ddim", 3),
                                                     ("diffusion", "ddim-clipped", 3), ("flow", "euler", 4),
                                                     ("flow", "euler", 1)])
def test_every_head_gives_the_same_result_shapes_and_entropy_semantics(objective, sampler, steps):
    """One sampler for every head: the same ``SampleResult`` shapes; a network whose output does not depend on the
    noisy input collapses all N samples for diffusion (x0 = its output: entropy 0.5·log ε, stride 1 with the
    release thresholds), while for flow the Euler steps of a constant velocity u end at ε − u, clipped to the
    normalised range (``flow.clip_sample``): N different samples whose entropy is the closed form
    mean 0.5·log(2πe·var + ε) of those values (near 0.5·log(2πe) ≈ 1.42 for unclipped unit noise)."""
    net = FakeNet()
    inference = InferenceConfig(num_samples=6, sampler=sampler, num_steps=steps)
    cfg = _cfg(steps=10, objective=objective)
    fn = make_sampler(net, cfg, 2, inference)
    params = {"w": jnp.float32(1.0), "v": jnp.float32(0.0)}
    res = fn(params, AffineNormalizer(jnp.float32(1.0)), _obs(), jax.random.key(0), RELEASE)
    assert res.chunks.shape == (2, 6, 12, 2) and res.actions.shape == (2, 4, 2)
    assert res.entropy.shape == res.stride.shape == res.freq_index.shape == (2,)
    assert res.stride.dtype == jnp.int32 and np.isin(np.asarray(res.stride), [1, 2, 3]).all()
    np.testing.assert_array_equal(np.asarray(res.actions),
                                  np.asarray(segment_of(cfg.chunk, res.chunks[:, 0], res.freq_index)))
    h = np.asarray(res.entropy)
    if objective == "diffusion":
        np.testing.assert_allclose(h, 0.5 * math.log(1e-6), rtol=1e-5)
    else:
        # sample i starts from ε_i = normal(split(split(key, N)[i])[1], (B, T, A)) (``denoise_chain``); the velocity
        # u = tanh(w·mean(obs)) (B,) is the same at every step, so K steps of dt = 1/K end at ε_i − u, then clipped
        u = np.tanh(np.asarray(_obs()["state"]).mean(axis=(1, 2, 3)))
        noise = np.stack([np.asarray(jax.random.normal(jax.random.split(k)[1], (2, 12, 2)))
                          for k in jax.random.split(jax.random.key(0), 6)], axis=1)  # (B, N, T, A)
        want = np.clip(noise - u[:, None, None, None], -1.0, 1.0)
        # float32: K ≤ 4 roundings of dt·u (~1e-7 each) per action, so 1e-5 leaves two orders of magnitude
        np.testing.assert_allclose(np.asarray(res.chunks), want, rtol=0, atol=1e-5)
        var = want.astype(np.float64).var(axis=1, ddof=1)  # (B, T, A), unbiased over the N = 6 samples
        # entropy: actions off by ~1e-7 move variances ≥ 0.02 by ≤ ~5e-6 relative, h ≈ 0.8..1.1 by ≤ ~3e-6: rtol 1e-5
        np.testing.assert_allclose(h, np.mean(0.5 * np.log(2 * np.pi * np.e * var + 1e-6), axis=(1, 2)), rtol=1e-5)
        assert np.all(h > 0.5 * math.log(1e-6) + 1.0)  # far above the collapsed samples' floor


@pytest.mark.parametrize("objective,sampler,steps", [("diffusion", "ddpm", 10), ("diffusion", "ddim", 3),
                                                     ("flow", "euler", 4), ("flow", "euler", 1)])
def test_prefix_inpainting_ends_on_the_committed_actions_for_every_head(objective, sampler, steps):
    """Asynchronous execution's inpainting: where the prefix is valid, the first d steps of every frequency's
    segment end equal to the committed actions (the last renoise is the clean prefix) and the entropy reads the
    free steps only; where it is not, the result is exactly the plain sampler's (every head, DDPM's noisy updates
    too), so one program serves decisions with and without committed actions."""
    net = FakeNet()
    cfg = _cfg(steps=10, objective=objective)
    inference = InferenceConfig(num_samples=6, sampler=sampler, num_steps=steps)
    fn = jax.jit(functools.partial(sample, net=net, cfg=cfg, action_dim=2, inference=inference))
    params = {"w": jnp.float32(0.5), "v": jnp.float32(0.3)}
    norm = AffineNormalizer(jnp.float32(2.0))
    prefix = jnp.asarray([[[0.3, -0.2], [0.1, 0.4]], [[9.0, 9.0], [9.0, 9.0]]], jnp.float32)  # (B=2, d=2, A=2)
    res = fn(params, norm, _obs(), jax.random.key(3), RELEASE, prefix=prefix, prefix_valid=jnp.array([True, False]))
    segs = np.asarray(res.chunks).reshape(2, 6, 3, 4, 2)  # (B, N, M, L_c, A)
    np.testing.assert_allclose(segs[0, :, :, :2], np.broadcast_to(np.asarray(prefix[0]), (6, 3, 2, 2)), atol=1e-5)
    assert np.abs(segs[1, :, :, :2] - 9.0).min() > 1.0  # not inpainted
    free = np.ones((3, 4), bool)
    free[:, :2] = False
    np.testing.assert_allclose(float(res.entropy[0]),
                               float(action_entropy(jnp.asarray(segs[0][:, free]))), rtol=1e-5)
    plain = fn(params, norm, _obs(), jax.random.key(3), RELEASE)
    for field in ("chunks", "entropy", "freq_index", "actions"):  # the not-inpainted row: the plain sampler's
        got, want = np.asarray(getattr(res, field)[1]), np.asarray(getattr(plain, field)[1])
        np.testing.assert_array_equal(got, want, field)
    assert not np.allclose(np.asarray(res.chunks[0]), np.asarray(plain.chunks[0]))
    with pytest.raises(ValueError, match=r"prefix: \(B, d, A\) with 1 <= d <= chunk_len=4"):
        fn(params, norm, _obs(), jax.random.key(3), RELEASE, prefix=jnp.zeros((2, 5, 2)))


def test_renoise_is_the_path_marginal_and_clean_after_the_last_step():
    """The heads' ``renoise``: diffusion's sqrt(ᾱ_prev)·x0 + sqrt(1−ᾱ_prev)·ε, flow's τ_next·ε + (1−τ_next)·x0; both
    give x0 itself after the last step."""
    from hipolicy_jax.heads import make_head
    from hipolicy_jax.heads.diffusion import alphas_cumprod
    x0, eps = jnp.full((1, 4, 2), 0.7), jnp.full((1, 4, 2), -1.3)
    cfg = _cfg(steps=10)
    plan = make_head(cfg).plan(InferenceConfig(sampler="ddim", num_steps=5))
    ab = alphas_cumprod(cfg.diffusion)
    row0 = jax.tree.map(lambda a: a[0], plan.table)  # t = 8 → the step leads to t = 6
    np.testing.assert_allclose(np.asarray(plan.renoise(row0, x0, eps))[0, 0, 0],
                               math.sqrt(ab[6]) * 0.7 - math.sqrt(1 - ab[6]) * 1.3, rtol=1e-5)
    last = jax.tree.map(lambda a: a[-1], plan.table)
    np.testing.assert_allclose(np.asarray(plan.renoise(last, x0, eps)), np.asarray(x0), rtol=1e-6)
    flow = make_head(_cfg(objective="flow")).plan(InferenceConfig(sampler="euler", num_steps=4))
    row0 = jax.tree.map(lambda a: a[0], flow.table)  # τ 1 → 0.75
    np.testing.assert_allclose(np.asarray(flow.renoise(row0, x0, eps))[0, 0, 0], 0.75 * -1.3 + 0.25 * 0.7, rtol=1e-6)
    last = jax.tree.map(lambda a: a[-1], flow.table)
    np.testing.assert_allclose(np.asarray(flow.renoise(last, x0, eps)), np.asarray(x0), rtol=1e-6)
