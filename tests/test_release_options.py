"""The training options that match the HiPolicy release and Diffusion Policy (DP): window padding
(``TrainConfig.max_action_pad`` against DP's ``SequenceSampler``), the learning-rate schedule (against diffusers'
cosine schedule), gradient clipping (against torch's ``clip_grad_norm_``), the EMA decay (against DP's
``EMAModel``) and each setting's error message.

The upstream numbers below are constants produced by the upstream code (DP at its unmodified source, torch 2.14.1,
diffusers 0.11.1); each constant's comment names the function and the command.
"""

import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from hipolicy_jax.config import ChunkConfig, TrainConfig
from hipolicy_jax.data import ReplayBuffer, SequenceDataset, sample_indices
from hipolicy_jax.data.dataset import train_heldout_datasets
from hipolicy_jax.data.windowing import action_offsets, obs_offsets
from hipolicy_jax.training import ema_decay, lr_schedule, make_optimizer


# ------------------------------------------------------------------------------------------------- window padding
# DP's create_indices(episode_ends, sequence_length, episode_mask, pad_before, pad_after) rows
# (buffer_start, buffer_end, sample_start, sample_end), from diffusion_policy/common/sampler.py run without its
# numba decorator: create_indices(np.array(ENDS), L, np.ones(len(ENDS), bool), pad_before, pad_after).tolist()
#
# Small chunk: strides (1, 2), L_h = 2, L_c = 3, δ = 1 -> obs_span 3, action_span 6, DP sequence 3 - 1 + 6 = 8,
# pad_before 2, pad_after 2. Episodes: 0..2 (3 frames), 3..6 (4), 7..13 (7).
SMALL_CHUNK = ChunkConfig(strides=(1, 2), obs_horizon=2, chunk_len=3, action_offset=1)
SMALL_ENDS = [3, 7, 14]
SMALL_DP_ROWS = [[3, 7, 2, 6], [7, 13, 2, 8], [7, 14, 1, 8], [7, 14, 0, 7], [8, 14, 0, 6]]  # L=8, 2, 2
# The release: default chunk (obs_span 7, action_span 23), its 29-frame sequence, pad_before 6, pad_after 7.
# Episodes: 0..14 (15 frames), 15..30 (16), 31..50 (20).
RELEASE_ENDS = [15, 31, 51]
RELEASE_DP_ROWS = [[15, 31, 6, 22], [31, 51, 6, 26], [31, 51, 5, 25], [31, 51, 4, 24], [31, 51, 3, 23],
                   [31, 51, 2, 22]]  # L=29, 6, 7


def dp_frames(row, sequence_length: int) -> list[int]:
    """The frame each position of DP's sampled sequence holds (``SequenceSampler.sample_sequence``: positions before
    sample_start repeat data[buffer_start], positions from sample_end repeat data[buffer_end - 1])."""
    bs, be, ss, se = row
    return [bs] * ss + list(range(bs, be)) + [be - 1] * (sequence_length - se)


def dp_windows(rows, chunk: ChunkConfig):
    """DP's rows as (current, obs_idx, act_idx) in our layout: the current frame at sequence position obs_span - 1."""
    seq = chunk.obs_span - 1 + chunk.action_span
    frames = np.array([dp_frames(r, seq) for r in rows], dtype=np.int64).reshape(len(rows), seq)
    now = chunk.obs_span - 1
    obs = frames[:, now + obs_offsets(chunk)]  # (S, M, L_h)
    act = frames[:, now + action_offsets(chunk)].reshape(len(rows), chunk.horizon)
    return frames[:, now], obs, act


def test_dp_rows_hand_computed():
    """The constants, by hand from create_indices: idx runs from -pad_before to L - sequence + pad_after."""
    # small: L = 3 -> idx ∈ [-2, 3 - 8 + 2 = -3]: none. L = 4 -> idx = -2: frames 3..6 at positions 2..5.
    # L = 7 -> idx ∈ [-2, 1]: start 7 + max(idx, 0), end 7 + min(idx + 8, 7), sample [max(-idx, 0), 8 - overrun).
    assert dp_frames(SMALL_DP_ROWS[0], 8) == [3, 3, 3, 4, 5, 6, 6, 6]
    assert [dp_frames(r, 8)[2] for r in SMALL_DP_ROWS] == [3, 7, 8, 9, 10]  # current frames t = idx + 2
    # release: L = 15 -> idx ∈ [-6, 15 - 29 + 7 = -7]: none; L = 16 -> idx = -6; L = 20 -> idx ∈ [-6, -2].
    assert [dp_frames(r, 29)[6] for r in RELEASE_DP_ROWS] == [15, 31, 32, 33, 34, 35]


def test_small_windows_equal_dp_sampler_index_for_index():
    with pytest.warns(UserWarning) as record:
        current, obs, act = sample_indices(np.array(SMALL_ENDS), SMALL_CHUNK, max_action_pad=2)
    dp_current, dp_obs, dp_act = dp_windows(SMALL_DP_ROWS, SMALL_CHUNK)
    np.testing.assert_array_equal(current, dp_current)
    np.testing.assert_array_equal(obs, dp_obs)
    np.testing.assert_array_equal(act, dp_act)
    # by hand: t ≤ end - action_span + 2 = end - 4; obs [t-2, t] | [t-1, t]; actions [t+1, t+3, t+5] | [t+1..t+3]
    np.testing.assert_array_equal(current, [3, 7, 8, 9, 10])
    np.testing.assert_array_equal(obs[0], [[3, 3], [3, 3]])
    np.testing.assert_array_equal(act[0], [4, 6, 6, 4, 5, 6])  # 2 padded frames past the last (6)
    np.testing.assert_array_equal(act[-1], [11, 13, 13, 11, 12, 13])
    assert [str(w.message) for w in record] == [
        "train.max_action_pad=2: a window needs an episode of at least 4 frames (chunk.action_span=6 - "
        "max_action_pad); episode 0 (3 frames) of the buffer's 3 is shorter and trains no window"]


def test_release_padding_stops_the_current_frame_at_end_minus_16():
    chunk = ChunkConfig()  # strides (1, 2, 3), L_h 3, L_c 8, δ 1: obs_span 7, action_span 23, DP sequence 29
    assert (chunk.obs_span, chunk.action_span, chunk.obs_span - 1 + chunk.action_span) == (7, 23, 29)
    with pytest.warns(UserWarning, match=r"episode 0 \(15 frames\) of the buffer's 3 is shorter"):
        current, obs, act = sample_indices(np.array(RELEASE_ENDS), chunk, max_action_pad=7)
    dp_current, dp_obs, dp_act = dp_windows(RELEASE_DP_ROWS, chunk)
    np.testing.assert_array_equal(current, dp_current)
    np.testing.assert_array_equal(obs, dp_obs)
    np.testing.assert_array_equal(act, dp_act)
    np.testing.assert_array_equal(current, [31 - 16] + list(range(31, 51 - 16 + 1)))  # t ≤ end - 16
    # the last window of episode 2 (t = 35): stride 3 reaches t + 22 = 57, 7 frames past its last frame 50
    np.testing.assert_array_equal(act[-1, :8], [36, 39, 42, 45, 48, 50, 50, 50])
    np.testing.assert_array_equal(act[-1, 8:16], [36, 38, 40, 42, 44, 46, 48, 50])  # stride 2: t + 15 = 50, real
    np.testing.assert_array_equal(act[-1, 16:], [36, 37, 38, 39, 40, 41, 42, 43])  # stride 1: all real


@pytest.mark.parametrize("strides,lh,lc,delta", [((1,), 2, 16, -1), ((1,), 2, 15, 0), ((1, 2), 2, 3, 1),
                                                 ((1, 2, 3), 3, 8, 1), ((2, 5), 1, 4, 0), ((1, 3), 4, 2, 1)])
def test_every_limit_gives_dp_samplers_windows(strides, lh, lc, delta):
    """For every limit p from 0 to (L_c - 1)·max(s) + min(δ, 0) (beyond it DP pads the current frame itself) and
    random episodes of 1-40 frames, the windows are DP's create_indices (the loop below restates it) with
    pad_before = obs_span - 1 and pad_after = p. ((1,), 2, 16, -1) is DP's low-dim layout (horizon 16 from the first
    observed frame, n_obs_steps 2; its pad_after n_action_steps - 1 = 7 is one of the p)."""
    chunk = ChunkConfig(strides=strides, obs_horizon=lh, chunk_len=lc, action_offset=delta)
    rng = np.random.default_rng(0)
    ends = np.cumsum(rng.integers(1, 41, size=12))
    seq, before = chunk.obs_span - 1 + chunk.action_span, chunk.obs_span - 1
    assert delta != -1 or seq == 16  # DP's horizon
    for pad in range((lc - 1) * max(strides) + min(delta, 0) + 1):
        rows = []
        for start, end in zip(np.concatenate([[0], ends[:-1]]), ends):
            length = end - start
            for idx in range(-before, length - seq + pad + 1):
                lo, hi = start + max(idx, 0), start + min(idx + seq, length)
                rows.append([lo, hi, lo - (idx + start), seq - ((idx + seq + start) - hi)])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            current, obs, act = sample_indices(ends, chunk, max_action_pad=pad)
        dp_current, dp_obs, dp_act = dp_windows(rows, chunk)
        np.testing.assert_array_equal(current, dp_current, err_msg=f"max_action_pad={pad}")
        np.testing.assert_array_equal(obs, dp_obs, err_msg=f"max_action_pad={pad}")
        np.testing.assert_array_equal(act, dp_act, err_msg=f"max_action_pad={pad}")


@pytest.mark.parametrize("delta", [0, 1])
def test_the_largest_useful_limit_is_no_limit(delta):
    """p = (L_c - 1)·max(s) lets every window whose first action is real train: the windows of None, except a
    1-frame episode with δ = 1 (its only window reaches action_span - 1 frames past it)."""
    chunk = ChunkConfig(action_offset=delta)
    ends = np.array([2, 9, 40, 100])
    unlimited = sample_indices(ends, chunk)
    for a, b in zip(sample_indices(ends, chunk, max_action_pad=(chunk.chunk_len - 1) * 3), unlimited):
        np.testing.assert_array_equal(a, b)
    # None: L - δ windows per episode
    np.testing.assert_array_equal(np.bincount(np.searchsorted(ends, unlimited[0], side="right")),
                                  np.diff(ends, prepend=0) - delta)
    lone = np.array([1, 30])
    if delta == 1:
        assert sample_indices(lone, chunk)[0].tolist()[0] == 0  # None: the 1-frame episode trains its first frame
        with pytest.warns(UserWarning, match=r"at least 2 frames .* episode 0 \(1 frames\)"):
            assert 0 not in sample_indices(lone, chunk, max_action_pad=21)[0]
        assert sample_indices(lone, chunk, max_action_pad=22)[0].tolist()[0] == 0


def test_a_negative_offset_keeps_every_current_frame_inside_its_episode():
    """DP's layout (δ = -1: the chunk starts at the observed frame before t): with no limit every frame of an episode
    is a current frame, and never the next episode's first; under DP's pad_after 7, t ≤ end - 15 + 7."""
    chunk = ChunkConfig(strides=(1,), obs_horizon=2, chunk_len=16, action_offset=-1)
    current, obs, act = sample_indices(np.array([5, 9]), chunk)
    np.testing.assert_array_equal(current, np.arange(9))
    np.testing.assert_array_equal(act[0], [0, 0, 1, 2, 3, 4] + [4] * 10)
    np.testing.assert_array_equal(act[5], [5, 5, 6, 7] + [8] * 12)
    np.testing.assert_array_equal(obs[4], [[3, 4]])
    current, _, _ = sample_indices(np.array([20, 28]), chunk, max_action_pad=7)
    np.testing.assert_array_equal(current, list(range(0, 13)) + [20])  # t ≤ 20 - 8, t ≤ 28 - 8


def test_no_episode_long_enough_is_an_error_naming_the_field_and_episodes():
    with pytest.raises(ValueError) as info:
        sample_indices(np.array([15, 29]), ChunkConfig(), max_action_pad=7)
    assert str(info.value) == (
        "train.max_action_pad=7: a window needs an episode of at least 16 frames (chunk.action_span=23 - "
        "max_action_pad); episodes 0 (15 frames), 1 (14 frames) of the buffer's 2 are shorter: no episode has a "
        "window (raise train.max_action_pad, or None for no limit)")
    with pytest.warns(UserWarning) as record:
        sample_indices(np.cumsum([3] * 12 + [20]), ChunkConfig(), max_action_pad=7)
    assert str(record[0].message).endswith("episodes 0 (3 frames), 1 (3 frames), 2 (3 frames), 3 (3 frames), "
                                           "4 (3 frames), 5 (3 frames), 6 (3 frames), 7 (3 frames), 8 (3 frames), "
                                           "9 (3 frames) and 2 more of the buffer's 13 are shorter and train no "
                                           "window")


def _buffer(lengths) -> ReplayBuffer:
    n = int(sum(lengths))
    t = np.arange(n, dtype=np.float32)
    return ReplayBuffer(data={"state": np.stack([t, -t], 1), "action": np.stack([t, 2 * t], 1)},
                        episode_ends=np.cumsum(lengths))


def test_datasets_take_the_limit_and_a_selection_without_windows_is_an_error():
    buf = _buffer([15, 16, 20, 30])
    with pytest.warns(UserWarning, match="episode 0"):
        ds = SequenceDataset(buf, ChunkConfig(), ("state",), max_action_pad=7)
    assert len(ds) == 0 + 1 + 5 + 15  # L - 15 windows where L ≥ 16 (t ≤ end - 16)
    assert len(SequenceDataset(buf, ChunkConfig(), ("state",))) == 14 + 15 + 19 + 29  # None: L - 1
    np.testing.assert_array_equal(ds.current[:6], [15, 31, 32, 33, 34, 35])
    with pytest.warns(UserWarning), pytest.raises(ValueError) as info:
        SequenceDataset(buf, ChunkConfig(), ("state",), episode_mask=np.array([True, False, False, False]),
                        max_action_pad=7)
    assert str(info.value) == ("train.max_action_pad=7: the selected episodes [0] are all too short for a window "
                               "(lengths [15], chunk.action_span=23); raise it, or None for no limit")
    train, val = train_heldout_datasets(buf, ChunkConfig(), ("state",), val_ratio=0.25, seed=0, max_action_pad=8)
    starts, ends = np.array([0, 15, 31, 51]), np.array([15, 31, 51, 81])
    for d in (train, val):  # both sides: t ≤ end - 23 + 8 = end - 15
        episode = np.searchsorted(ends, d.current, side="right")
        assert (d.current <= ends[episode] - 15).all() and (d.current >= starts[episode]).all()
    assert len(train) + len(val) == 1 + 2 + 6 + 16


# ------------------------------------------------------------------------------------------------------- schedule
# diffusers.optimization.get_scheduler("cosine", optimizer, num_warmup_steps=W, num_training_steps=N), driven as DP's
# workspace drives it (optimizer.step(); lr_scheduler.step()): the lr update k (1-based) uses, lr 1e-4. Command:
#   o = torch.optim.AdamW([torch.nn.Parameter(torch.zeros(1))], lr=1e-4)
#   s = get_scheduler("cosine", o, num_warmup_steps=W, num_training_steps=N)
#   for k in range(1, N + 1): record(k, o.param_groups[0]["lr"]); o.step(); s.step()
DIFFUSERS_LR = {
    (500, 3000): {1: 0.0, 2: 2.0000000000000002e-07, 250: 4.9800000000000004e-05, 500: 9.98e-05, 501: 0.0001,
                  1000: 9.048774940693062e-05, 1750: 5.006283183653513e-05, 2999: 1.57913587295333e-10,
                  3000: 3.9478412411364515e-11},
    (20, 100): {1: 0.0, 2: 5e-06, 10: 4.5e-05, 20: 9.5e-05, 21: 0.0001, 22: 9.996145181203615e-05,
                60: 5.196299078795344e-05, 99: 1.5413331334360182e-07, 100: 3.8548187963854956e-08},
    (8000, 3000): {1: 0.0, 2: 1.2500000000000001e-08, 1500: 1.87375e-05, 3000: 3.74875e-05},  # the release's v1
}


def diffusers_cosine(k: int, warmup: int, total: int, lr: float = 1e-4) -> float:
    """get_cosine_schedule_with_warmup's lr_lambda at k - 1 (the formula, restated), times lr."""
    c = k - 1
    if c < warmup:
        return lr * c / max(1, warmup)
    return lr * max(0.0, 0.5 * (1.0 + math.cos(math.pi * (c - warmup) / max(1, total - warmup))))


@pytest.mark.parametrize("warmup,total", list(DIFFUSERS_LR))
def test_lr_schedule_is_diffusers_cosine_with_warmup(warmup, total):
    sched = lr_schedule(TrainConfig(lr=1e-4, warmup_steps=warmup, num_steps=total))
    for k, expected in DIFFUSERS_LR[(warmup, total)].items():
        assert diffusers_cosine(k, warmup, total) == pytest.approx(expected, rel=1e-12, abs=1e-20)
        # float32: 1e-6 of lr absolute (the cosine's tail), 1e-4 relative (1 - 1/500 rounding in the warm-up)
        assert float(sched(k - 1)) == pytest.approx(expected, rel=1e-4, abs=1e-10), f"update {k}"


def test_the_optimizer_applies_update_ks_learning_rate_to_update_k():
    """A constant gradient of 1 and no weight decay: Adam's m̂ = 1, v̂ = 1, so update k moves the parameter by
    -lr_k / (1 + 1e-8) exactly; lr_k from diffusers (warm-up 20 of 100)."""
    tx = make_optimizer(TrainConfig(lr=1e-4, warmup_steps=20, num_steps=100, weight_decay=0.0))

    def one(carry, _):
        p, s = carry
        u, s = tx.update(jnp.ones(1), s, p)
        return (p + u, s), u[0]

    p0 = jnp.zeros(1)
    _, moves = jax.lax.scan(one, (p0, tx.init(p0)), None, length=100)
    for k, lr_k in DIFFUSERS_LR[(20, 100)].items():
        assert -float(moves[k - 1]) == pytest.approx(lr_k / (1 + 1e-8), rel=1e-4, abs=1e-10), f"update {k}"


# ------------------------------------------------------------------------------------------------------- clipping
# torch.nn.utils.clip_grad_norm_(params, 1.0) on grads ([3, 4] * scale / 5, [0]) (global norm = scale):
#   returned norm and clipped grads, torch 2.14.1 (clip coefficient max_norm / (norm + 1e-6), at most 1)
TORCH_CLIPPED = {0.5: [[0.30000001192092896, 0.4000000059604645], [0.0]],
                 1.0: [[0.5999994277954102, 0.7999992370605469], [0.0]],
                 3.0: [[0.5999997854232788, 0.7999997735023499], [0.0]]}


@pytest.mark.parametrize("scale", list(TORCH_CLIPPED))
def test_clip_by_global_norm_is_torchs_clip_grad_norm(scale):
    grads = {"a": jnp.array([3.0, 4.0]) * scale / 5, "b": jnp.zeros(1)}
    clipped, _ = optax.clip_by_global_norm(1.0).update(grads, optax.EmptyState())
    # equal but for torch's 1e-6 in the denominator: relative 1e-6 / norm
    np.testing.assert_allclose(clipped["a"], TORCH_CLIPPED[scale][0], rtol=2e-6)
    np.testing.assert_array_equal(clipped["b"], TORCH_CLIPPED[scale][1])


@pytest.mark.parametrize("grad_clip", [None, 1.0])
def test_clipping_comes_before_adamw_with_the_configured_betas(grad_clip):
    """Two updates with gradients of global norm 3 then 0.5 and the release's betas (0.9, 0.999): Adam's second
    update in closed form, on the gradients clipped to norm 1 (torch: clip_grad_norm_ then AdamW.step) or raw."""
    cfg = TrainConfig(lr=1e-4, warmup_steps=0, num_steps=1000, weight_decay=0.0, betas=(0.9, 0.999),
                      grad_clip=grad_clip)
    tx = make_optimizer(cfg)
    unit = jnp.array([0.6, 0.8])
    g1, g2 = 3.0 * unit, 0.5 * unit
    p = jnp.zeros(2)
    state = tx.init(p)
    _, state = tx.update(g1, state, p)
    second, _ = tx.update(g2, state, p)
    b1, b2, eps = 0.9, 0.999, 1e-8
    c1 = np.asarray(g1 if grad_clip is None else unit, np.float64)  # norm 3 -> 1; norm 0.5 stays
    c2 = np.asarray(g2, np.float64)
    m = (b1 * (1 - b1) * c1 + (1 - b1) * c2) / (1 - b1 ** 2)
    v = (b2 * (1 - b2) * c1 ** 2 + (1 - b2) * c2 ** 2) / (1 - b2 ** 2)
    lr2 = diffusers_cosine(2, 0, 1000)
    # rtol 1e-4: float32 bias corrections (1 - 0.999² cancels to 3e-5 relative); clipped is 1.19x raw here
    np.testing.assert_allclose(second, -lr2 * m / (np.sqrt(v) + eps), rtol=1e-4)


# ------------------------------------------------------------------------------------------------------------ EMA
# diffusion_policy/model/diffusion/ema_model.py: EMAModel(model, update_after_step=0, inv_gamma=1.0, power=0.75,
# min_value=0.0, max_value=0.9999).get_decay(n). Command:
#   e = EMAModel(torch.nn.Linear(1, 1), power=0.75); {n: e.get_decay(n) for n in (0, 1, 2, ...)}
DP_GET_DECAY = {0: 0.0, 1: 0.0, 2: 0.4053964424986395, 3: 0.5613086623491692, 4: 0.6464466094067263,
                9: 0.8075499102701247, 99: 0.9681379581259606, 999: 0.9943723654944067, 9999: 0.9989999249934369,
                215443: 0.9998999998367307, 215444: 0.9999}
# The decay DP's workspace applies at update k = 1..5 (ema.step(model) after each optimizer.step(); EMAModel.step
# sets self.decay = get_decay(self.optimization_step) and then counts the update): get_decay(k - 1).
DP_WORKSPACE_DECAY = {1: 0.0, 2: 0.0, 3: 0.4053964424986395, 4: 0.5613086623491692, 5: 0.6464466094067263}


def test_ema_decay_is_dp_get_decay_applied_as_dps_workspace_applies_it():
    cfg = TrainConfig()
    for n, expected in DP_GET_DECAY.items():
        expected_formula = 0.0 if n <= 1 else min(1 - n ** -0.75, 0.9999)  # 1 - (1 + s)^-0.75, s = n - 1
        assert expected_formula == pytest.approx(expected, rel=1e-12, abs=0)
        assert float(ema_decay(n, cfg)) == pytest.approx(expected, abs=1e-6), f"step {n}"
    assert float(ema_decay(10 ** 7, cfg)) == pytest.approx(0.9999, abs=1e-7)  # max_value
    # the train step applies ema_decay(updates before this one) = get_decay(k - 1) at update k, as DP's workspace
    for k, dp_at_k in DP_WORKSPACE_DECAY.items():
        assert float(ema_decay(k - 1, cfg)) == pytest.approx(dp_at_k, abs=1e-6)


def test_ema_decay_follows_power_and_max_decay():
    cfg = TrainConfig(ema_power=2 / 3, ema_max_decay=0.999)  # EMAModel's own defaults: power 2/3
    assert float(ema_decay(8, cfg)) == pytest.approx(1 - 8 ** (-2 / 3), abs=1e-6)  # = 0.75
    assert float(ema_decay(10 ** 6, cfg)) == pytest.approx(0.999, abs=1e-7)


# --------------------------------------------------------------------------------------------- defaults and errors
def test_defaults_are_dps():
    cfg = TrainConfig()
    assert (cfg.betas, cfg.warmup_steps, cfg.grad_clip, cfg.ema, cfg.ema_power, cfg.ema_max_decay,
            cfg.max_action_pad) == ((0.95, 0.999), 500, None, True, 0.75, 0.9999, None)


@pytest.mark.parametrize("field,value,message", [
    ("betas", (0.9,), "train.betas: must be two values in [0, 1), got (0.9,)"),
    ("betas", (0.9, 1.0), "train.betas: must be two values in [0, 1), got (0.9, 1.0)"),
    ("warmup_steps", -1, "train.warmup_steps: must be >= 0, got -1"),
    ("grad_clip", 0.0, "train.grad_clip: must be None (no clipping) or > 0, got 0.0"),
    ("grad_clip", -1.0, "train.grad_clip: must be None (no clipping) or > 0, got -1.0"),
    ("ema_power", 0.0, "train.ema_power: must be > 0, got 0.0"),
    ("ema_max_decay", 1.0, "train.ema_max_decay: must be in [0, 1), got 1.0"),
    ("ema_max_decay", -0.1, "train.ema_max_decay: must be in [0, 1), got -0.1"),
    ("max_action_pad", -1, "train.max_action_pad: must be None (no limit) or >= 0, got -1"),
])
def test_each_bad_value_is_refused_with_its_message(field, value, message):
    with pytest.raises(ValueError) as info:
        TrainConfig(**{field: value})
    assert str(info.value) == message


def test_the_release_settings_are_accepted():
    v1 = TrainConfig(betas=(0.9, 0.999), warmup_steps=8000, grad_clip=1.0, ema=False, max_action_pad=7)
    v2 = TrainConfig(betas=(0.9, 0.999), warmup_steps=500, ema=True, max_action_pad=7)
    assert (v1.grad_clip, v1.ema, v2.grad_clip, v2.max_action_pad) == (1.0, False, None, 7)
