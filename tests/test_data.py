"""Data stages: replay buffer, multi-frequency windowing, normalisation, dataset batching.

Most expectations are hand-computed for a two-episode buffer: episode 0 = frames 0..4, episode 1 = frames 5..8
(``episode_ends = [5, 9]``).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import zarr

from hipolicy_jax.config import ChunkConfig
from hipolicy_jax.data import (Normalizer, ReplayBuffer, SequenceDataset, gather_history, history_window_indices,
                               image_to_float, sample_indices, split_episodes)

ENDS = np.array([5, 9], dtype=np.int64)
# strides (1, 2) -> segment order (2, 1); L_h = 2, L_c = 3
SMALL = dict(strides=(1, 2), obs_horizon=2, chunk_len=3)


def small_buffer(image: bool = False, point_cloud: bool = False) -> ReplayBuffer:
    """9 frames, episodes [0..4] and [5..8]; action[t] = (t, 1.5) (second dim constant), state[t] = (10t, -t)."""
    t = np.arange(9, dtype=np.float32)
    data = {"action": np.stack([t, np.full(9, 1.5, np.float32)], axis=1),
            "state": np.stack([10 * t, -t], axis=1)}
    if image:
        data["image"] = np.broadcast_to((10 * np.arange(9, dtype=np.uint8))[:, None, None, None], (9, 4, 4, 3)).copy()
    if point_cloud:
        data["point_cloud"] = np.broadcast_to(t[:, None, None], (9, 5, 3)).astype(np.float32).copy()
    return ReplayBuffer(data=data, episode_ends=ENDS)


# ------------------------------------------------------------------------------------------------------ windowing
def test_sample_indices_hand_computed_offset_1():
    current, obs, act = sample_indices(ENDS, ChunkConfig(**SMALL, action_offset=1))
    # δ = 1: the last frame of each episode (4, 8) has no real next action, so it is not a sample.
    np.testing.assert_array_equal(current, [0, 1, 2, 3, 5, 6, 7])
    assert obs.shape == (7, 2, 2) and act.shape == (7, 6)
    # obs rows: stride 2 [t-2, t], stride 1 [t-1, t]; front padding repeats the episode's first frame.
    np.testing.assert_array_equal(obs, [
        [[0, 0], [0, 0]],
        [[0, 1], [0, 1]],
        [[0, 2], [1, 2]],
        [[1, 3], [2, 3]],
        [[5, 5], [5, 5]],  # episode 1 starts at 5: never reads frame 4 of episode 0
        [[5, 6], [5, 6]],
        [[5, 7], [6, 7]],
    ])
    # act: stride-2 segment [t+1, t+3, t+5] | stride-1 segment [t+1, t+2, t+3]; back padding repeats the last frame.
    np.testing.assert_array_equal(act, [
        [1, 3, 4, 1, 2, 3],
        [2, 4, 4, 2, 3, 4],
        [3, 4, 4, 3, 4, 4],  # never reads frame 5 of episode 1
        [4, 4, 4, 4, 4, 4],
        [6, 8, 8, 6, 7, 8],
        [7, 8, 8, 7, 8, 8],
        [8, 8, 8, 8, 8, 8],
    ])


def test_sample_indices_hand_computed_offset_0():
    current, obs, act = sample_indices(ENDS, ChunkConfig(**SMALL, action_offset=0))
    np.testing.assert_array_equal(current, np.arange(9))  # every frame is a sample
    np.testing.assert_array_equal(act[0], [0, 2, 4, 0, 1, 2])
    np.testing.assert_array_equal(obs[4], [[2, 4], [3, 4]])
    np.testing.assert_array_equal(act[4], [4, 4, 4, 4, 4, 4])
    np.testing.assert_array_equal(obs[5], [[5, 5], [5, 5]])
    np.testing.assert_array_equal(act[5], [5, 7, 8, 5, 6, 7])
    np.testing.assert_array_equal(obs[8], [[6, 8], [7, 8]])
    np.testing.assert_array_equal(act[8], [8, 8, 8, 8, 8, 8])


def test_short_episodes_train_with_padded_windows_at_both_edges():
    """The default windowing (strides 1/2/3, L_h 3, L_c 8, δ 1: 7 frames of history, 23 of actions) on episodes of
    1 and 2 frames: observation history before the first frame repeats it, actions past the last frame repeat it."""
    chunk = ChunkConfig()
    assert chunk.obs_span == 7 and chunk.action_span == 23
    current, obs, act = sample_indices(np.array([1, 3]), chunk)
    # episode 0 = frame 0 alone: with δ = 1 it has no next action, yet its frame trains on the last (only) action
    # episode 1 = frames 1, 2: frame 1 is a sample (its next action, frame 2, exists); frame 2 has none
    np.testing.assert_array_equal(current, [0, 1])
    np.testing.assert_array_equal(obs, [np.zeros((3, 3)), np.ones((3, 3))])
    np.testing.assert_array_equal(act, [np.zeros(24), np.full(24, 2)])
    # with δ = 0 every frame is a sample; frame 2's history is [1, 1, 2] at stride 1, [1, 1, 2] at 2 and 3
    current, obs, act = sample_indices(np.array([1, 3]), ChunkConfig(action_offset=0))
    np.testing.assert_array_equal(current, [0, 1, 2])
    np.testing.assert_array_equal(obs[2], [[1, 1, 2], [1, 1, 2], [1, 1, 2]])
    np.testing.assert_array_equal(act[1], np.tile([1, 2, 2, 2, 2, 2, 2, 2], 3))  # each stride: a[1], then a[2]
    np.testing.assert_array_equal(act[2], np.full(24, 2))


def test_a_short_episode_trains_beside_long_ones():
    """A dataset of one 1-frame episode and one 30-frame one: both give samples, and batches read only real frames."""
    t = np.arange(31, dtype=np.float32)
    buf = ReplayBuffer(data={"action": t[:, None], "state": 10 * t[:, None]}, episode_ends=np.array([1, 31]))
    ds = SequenceDataset(buf, ChunkConfig(), obs_keys=("state",))
    assert len(ds) == 1 + 29 and ds.current[0] == 0
    raw = ds.normalizer.unnormalize("action", ds.get_batch(np.array([0]))["action"])
    np.testing.assert_allclose(raw, np.zeros((1, 24, 1)), atol=1e-5)


def test_single_stride_is_plain_diffusion_policy_window():
    current, obs, act = sample_indices(ENDS, ChunkConfig(strides=(1,), obs_horizon=2, chunk_len=4, action_offset=0))
    assert obs.shape == (9, 1, 2) and act.shape == (9, 4)
    # Episode 1 (frames 5..8): DP pads n_obs-1 = 1 frame before and repeats the last action after.
    np.testing.assert_array_equal(obs[5:, 0], [[5, 5], [5, 6], [6, 7], [7, 8]])
    np.testing.assert_array_equal(act[5:], [[5, 6, 7, 8], [6, 7, 8, 8], [7, 8, 8, 8], [8, 8, 8, 8]])


@pytest.mark.parametrize("strides, lh, lc, delta", [((1, 2, 3), 3, 8, 1), ((1, 4), 2, 4, 0), ((2,), 1, 3, 1)])
def test_sample_indices_match_the_definition_and_stay_in_episode(strides, lh, lc, delta):
    chunk = ChunkConfig(strides=strides, obs_horizon=lh, chunk_len=lc, action_offset=delta)
    ends = np.cumsum([1, 7, 2, 30, 4])
    current, obs, act = sample_indices(ends, chunk)
    starts = np.concatenate([[0], ends[:-1]])
    # every frame whose first action lies in its episode; a 1-frame episode with δ = 1 still gives its frame
    expected_current = [t for s, e in zip(starts, ends) for t in range(s, e) if t + delta <= e - 1 or t == s]
    np.testing.assert_array_equal(current, expected_current)
    for row, t in enumerate(current):
        ep = int(np.searchsorted(ends, t, side="right"))
        lo, hi = starts[ep], ends[ep] - 1
        for m, s in enumerate(sorted(strides, reverse=True)):
            want_obs = [min(max(t - (lh - 1 - j) * s, lo), hi) for j in range(lh)]
            want_act = [min(max(t + delta + j * s, lo), hi) for j in range(lc)]
            np.testing.assert_array_equal(obs[row, m], want_obs)
            np.testing.assert_array_equal(act[row, m * lc:(m + 1) * lc], want_act)
        assert lo <= obs[row].min() and obs[row].max() <= hi
        assert lo <= act[row].min() and act[row].max() <= hi


def test_history_window_indices_default_config():
    chunk = ChunkConfig()
    assert chunk.obs_span == 7
    np.testing.assert_array_equal(history_window_indices(chunk), [[0, 3, 6], [2, 4, 6], [4, 5, 6]])
    np.testing.assert_array_equal(history_window_indices(ChunkConfig(strides=(1,), obs_horizon=2)), [[0, 1]])


def test_gather_history_agrees_with_sample_indices_under_jit_and_vmap():
    chunk = ChunkConfig()
    frames = np.arange(40 * 2, dtype=np.float32).reshape(40, 2)  # one 40-frame episode
    current, obs_idx, _ = sample_indices(np.array([40]), chunk)
    ts = np.array([10, 20, 31])
    histories = {"state": jnp.stack([frames[t - 6:t + 1] for t in ts])}  # (3, obs_span, 2)
    got = jax.jit(jax.vmap(lambda h: gather_history(h, chunk)))(histories)["state"]
    assert got.shape == (3, 3, 3, 2)
    for b, t in enumerate(ts):
        row = int(np.flatnonzero(current == t)[0])
        np.testing.assert_array_equal(np.asarray(got[b]), frames[obs_idx[row]])
    # t = 20: long [14, 17, 20], mid [16, 18, 20], short [18, 19, 20]; first feature of frame f is 2f.
    np.testing.assert_array_equal(np.asarray(got[1, :, :, 0]), [[28, 34, 40], [32, 36, 40], [36, 38, 40]])
    with pytest.raises(ValueError, match="state"):
        gather_history({"state": jnp.zeros((6, 2))}, chunk)


# ----------------------------------------------------------------------------------------------------- normaliser
def test_normalizer_hand_computed_limits_round_trip_and_constant_dims():
    x = np.array([[-2.0, 3.0, 0.0], [6.0, 3.0, 1.0], [2.0, 3.0, 0.5]], dtype=np.float32)
    norm = Normalizer.fit({"state": x})
    # dim 0: range 8 -> scale 0.25, offset -0.5; dim 1 constant -> scale 1, offset -3; dim 2: scale 2, offset -1.
    np.testing.assert_allclose(norm.stats["state"]["scale"], [0.25, 1.0, 2.0])
    np.testing.assert_allclose(norm.stats["state"]["offset"], [-0.5, -3.0, -1.0])
    y = norm.normalize("state", x)
    np.testing.assert_allclose(y, [[-1, 0, -1], [1, 0, 1], [0, 0, 0]], atol=1e-6)
    assert y.dtype == np.float32 and np.all(np.isfinite(y))
    np.testing.assert_allclose(norm.unnormalize("state", y), x, atol=1e-6)
    # a constant dim stays finite and at 0 even away from its value; range below range_eps counts as constant
    tiny = Normalizer.fit({"a": np.array([[1.0], [1.00005]])})
    np.testing.assert_allclose(tiny.stats["a"]["scale"], [1.0])
    np.testing.assert_allclose(tiny.normalize("a", np.array([[1.0]])), [[0.0]])


def test_normalizer_point_cloud_per_channel_jit_and_dict_round_trip():
    pc = np.zeros((2, 3, 3), dtype=np.float32)
    pc[0, :, 0] = [0, 1, 2]
    pc[1, :, 0] = [4, 3, 3]  # channel 0 spans [0, 4] over frames and points
    pc[..., 1] = 5.0  # constant channel
    pc[1, 2, 2] = -1.0  # channel 2 spans [-1, 0]
    norm = Normalizer.fit({"point_cloud": pc, "image": np.zeros((2, 4, 4, 3), np.uint8)})
    assert set(norm.stats) == {"point_cloud"}  # images are never fitted
    np.testing.assert_allclose(norm.stats["point_cloud"]["min"], [0, 5, -1])
    np.testing.assert_allclose(norm.stats["point_cloud"]["max"], [4, 5, 0])
    y = jax.jit(lambda n, v: n.normalize("point_cloud", v))(norm, jnp.asarray(pc))
    np.testing.assert_allclose(np.asarray(y[0, :, 0]), [-1, -0.5, 0], atol=1e-6)
    np.testing.assert_allclose(np.asarray(y[..., 1]), 0.0)
    restored = Normalizer.from_dict(norm.to_dict())
    np.testing.assert_allclose(restored.unnormalize("point_cloud", np.asarray(y)), pc, atol=1e-6)
    with pytest.raises(ValueError, match="image"):
        Normalizer.fit({"image": np.zeros((2, 4, 4, 3), np.uint8)}, keys=["image"])


def test_image_to_float_and_normalize_obs():
    img = np.array([0, 51, 255], dtype=np.uint8)
    np.testing.assert_allclose(image_to_float(img), [-1.0, -0.6, 1.0], atol=1e-6)
    norm = Normalizer.fit({"state": np.array([[0.0], [2.0]])})
    out = norm.normalize_obs({"state": np.array([[1.0]]), "image": img})
    np.testing.assert_allclose(out["state"], [[0.0]])
    np.testing.assert_allclose(out["image"], [-1.0, -0.6, 1.0], atol=1e-6)
    with pytest.raises(KeyError, match="agent_pos"):
        norm.normalize_obs({"agent_pos": np.zeros((1, 2), np.float32)})


# -------------------------------------------------------------------------------------------------- replay buffer
def test_replay_buffer_episodes_and_zarr_round_trip(tmp_path):
    buf = small_buffer(image=True)
    assert buf.num_episodes == 2 and buf.num_frames == 9
    np.testing.assert_array_equal(buf.episode_lengths(), [5, 4])
    assert buf.episode_slice(1) == slice(5, 9)
    np.testing.assert_array_equal(buf.get_episode(1)["action"][:, 0], [5, 6, 7, 8])
    rebuilt = ReplayBuffer.from_episodes([buf.get_episode(0), buf.get_episode(1)])
    np.testing.assert_array_equal(rebuilt.episode_ends, [5, 9])
    assert rebuilt.episode_ends.dtype == np.int64

    path = tmp_path / "buf.zarr"
    buf.save(path)
    root = zarr.open_group(str(path), mode="r")
    assert sorted(root["data"].array_keys()) == ["action", "image", "state"]
    np.testing.assert_array_equal(root["meta"]["episode_ends"][...], [5, 9])
    loaded = ReplayBuffer.load(path)
    for key in buf.data:
        np.testing.assert_array_equal(loaded.data[key], buf.data[key])
        assert loaded.data[key].dtype == buf.data[key].dtype
    assert set(ReplayBuffer.load(path, keys=["state"]).data) == {"state"}
    with pytest.raises(ValueError, match="point_cloud"):
        ReplayBuffer.load(path, keys=["point_cloud"])

    with pytest.raises(FileExistsError, match="overwrite"):
        buf.save(path)
    ReplayBuffer.from_episodes([buf.get_episode(1)]).save(path, overwrite=True)
    np.testing.assert_array_equal(ReplayBuffer.load(path).episode_ends, [4])


def test_load_validates(tmp_path):
    path = str(tmp_path / "bad.zarr")
    root = zarr.open_group(path, mode="w")
    root.create_group("data").create_array("state", data=np.zeros((6, 2), np.float32))
    root.create_group("meta").create_array("episode_ends", data=np.array([2, 5], np.int64))
    with pytest.raises(ValueError, match=r"episode_ends.*6.*5"):
        ReplayBuffer.load(path)


@pytest.mark.parametrize("data, ends, pattern", [
    ({"state": np.zeros((4, 2), np.float32)}, np.array([2.0, 4.0]), r"episode_ends.*integer.*float64"),
    ({"state": np.zeros((4, 2), np.float32)}, np.array([3, 2, 4]), r"episode_ends.*strictly increasing"),
    ({"state": np.zeros((4, 2), np.float32)}, np.array([2, 5]), r"episode_ends.*4.*got 5"),
    ({"state": np.zeros((4, 2), np.float32), "action": np.zeros((3, 1), np.float32)}, np.array([4]),
     r"'action'.*3 frames, expected 4"),
    ({"image": np.zeros((4, 8, 8, 3), np.float32)}, np.array([4]), r"'image'.*uint8"),
    ({"point_cloud": np.zeros((4, 10, 4), np.float32)}, np.array([4]), r"'point_cloud'.*\(T, P, 3 or 6\)"),
    ({}, np.array([4]), "empty"),
    ({"state": np.zeros((4, 2), np.float32)}, np.array([], np.int64), r"episode_ends.*empty"),
])
def test_replay_buffer_validation_errors(data, ends, pattern):
    with pytest.raises(ValueError, match=pattern):
        ReplayBuffer(data=data, episode_ends=ends)


def test_replay_buffer_reports_first_non_finite_frame():
    state = np.zeros((6, 2), np.float32)
    state[3, 1] = np.inf
    state[5, 0] = np.nan
    with pytest.raises(ValueError, match=r"'state'.*NaN or Inf.*first bad frame index 3"):
        ReplayBuffer(data={"state": state}, episode_ends=np.array([6]))
    with pytest.raises(ValueError, match=r"episode 1.*'action'.*2 frames, expected 3"):
        ReplayBuffer.from_episodes([{"state": np.zeros((2, 1)), "action": np.zeros((2, 1))},
                                    {"state": np.zeros((3, 1)), "action": np.zeros((2, 1))}])


# -------------------------------------------------------------------------------------------------------- dataset
def test_get_batch_shapes_and_hand_computed_values():
    buf = small_buffer(image=True, point_cloud=True)
    chunk = ChunkConfig(**SMALL, action_offset=1)
    ds = SequenceDataset(buf, chunk, obs_keys=("image", "point_cloud", "state"))
    assert len(ds) == 7
    batch = ds.get_batch(np.array([0, 2, 6]))
    assert batch["action"].shape == (3, 6, 2) and batch["action"].dtype == np.float32
    assert batch["obs"]["image"].shape == (3, 2, 2, 4, 4, 3) and batch["obs"]["image"].dtype == np.float32
    assert batch["obs"]["point_cloud"].shape == (3, 2, 2, 5, 3)
    assert batch["obs"]["state"].shape == (3, 2, 2, 2)
    # action dim 0 = frame index over [0, 8] -> f/4 - 1; sample 0 (t=0) reads frames [1, 3, 4 | 1, 2, 3].
    np.testing.assert_allclose(batch["action"][0, :, 0], [-0.75, -0.25, 0.0, -0.75, -0.5, -0.25], atol=1e-6)
    np.testing.assert_allclose(batch["action"][..., 1], 0.0)  # constant dim
    # sample 2 (t=2): image frames stride 2 [0, 2], stride 1 [1, 2]; pixel = 10 f -> 20 f / 255 - 1.
    np.testing.assert_allclose(batch["obs"]["image"][1, :, :, 0, 0, 0],
                               [[-1.0, 40 / 255 - 1], [20 / 255 - 1, 40 / 255 - 1]], atol=1e-6)
    # state dim 1 = -f over [-8, 0] -> 1 - f/4; sample 6 (t=7): stride 2 frames [5, 7], stride 1 frames [6, 7].
    np.testing.assert_allclose(batch["obs"]["state"][2, :, :, 1], [[-0.25, -0.75], [-0.5, -0.75]], atol=1e-6)


def test_dataset_missing_keys_and_small_dataset_errors():
    buf = small_buffer()
    chunk = ChunkConfig(**SMALL)
    with pytest.raises(ValueError, match=r"'image'.*\(T, H, W, 3\) uint8"):
        SequenceDataset(buf, chunk, obs_keys=("image",))
    no_action = ReplayBuffer(data={"state": buf.data["state"]}, episode_ends=ENDS)
    with pytest.raises(ValueError, match=r"'action'.*\(T, A\)"):
        SequenceDataset(no_action, chunk, obs_keys=("state",))
    ds = SequenceDataset(buf, chunk, obs_keys=("state",))
    with pytest.raises(ValueError, match=r"7 samples.*batch_size=8"):
        ds.batch_indices(jax.random.key(0), 0, 8)


def test_split_and_masked_dataset_fit_only_their_episodes():
    train, val = split_episodes(10, 0.2, seed=3)
    assert train.sum() == 8 and val.sum() == 2 and not np.any(train & val)
    np.testing.assert_array_equal(split_episodes(10, 0.2, seed=3)[1], val)
    train_mask = np.array([False, True])  # train on episode 1 (frames 5..8) only
    chunk = ChunkConfig(**SMALL, action_offset=1)
    tr = SequenceDataset(small_buffer(), chunk, ("state",), episode_mask=train_mask)
    np.testing.assert_array_equal(tr.current, [5, 6, 7])
    np.testing.assert_allclose(tr.normalizer.stats["action"]["min"], [5, 1.5])
    np.testing.assert_allclose(tr.normalizer.stats["action"]["max"], [8, 1.5])
    va = SequenceDataset(small_buffer(), chunk, ("state",), episode_mask=~train_mask, normalizer=tr.normalizer)
    np.testing.assert_array_equal(va.current, [0, 1, 2, 3])
    # frame 1 in the training normaliser's units: 2 (1 - 5) / 3 - 1 = -11/3
    np.testing.assert_allclose(va.get_batch(np.array([0]))["action"][0, 0, 0], -11 / 3, atol=1e-5)


def test_batch_indices_resumable_and_cover_each_epoch_once():
    ends = np.array([30, 50])  # δ = 1 -> 29 + 19 = 48 samples; batch 8 -> 6 steps per epoch
    t = np.arange(50, dtype=np.float32)[:, None]
    buf = ReplayBuffer(data={"state": t, "action": t}, episode_ends=ends)
    chunk = ChunkConfig(**SMALL, action_offset=1)
    key = jax.random.key(7)
    ds = SequenceDataset(buf, chunk, ("state",))
    assert len(ds) == 48 and ds.steps_per_epoch(8) == 6
    epoch0 = np.concatenate([ds.batch_indices(key, s, 8) for s in range(6)])
    epoch1 = np.concatenate([ds.batch_indices(key, s, 8) for s in range(6, 12)])
    np.testing.assert_array_equal(np.sort(epoch0), np.arange(48))
    np.testing.assert_array_equal(np.sort(epoch1), np.arange(48))
    assert not np.array_equal(epoch0, epoch1)
    restarted = SequenceDataset(ReplayBuffer(data={"state": t, "action": t}, episode_ends=ends), chunk, ("state",))
    for step in (0, 5, 9, 1000):
        np.testing.assert_array_equal(restarted.batch_indices(jax.random.key(7), step, 8),
                                      ds.batch_indices(key, step, 8))
    assert not np.array_equal(ds.batch_indices(jax.random.key(8), 0, 8), ds.batch_indices(key, 0, 8))
    # batch 9: 5 full batches per epoch (45 distinct samples), the last 3 samples of the permutation are dropped
    assert ds.steps_per_epoch(9) == 5
    epoch0_b9 = np.concatenate([ds.batch_indices(key, s, 9) for s in range(5)])
    assert len(np.unique(epoch0_b9)) == 45


def test_steps_at_bound_is_each_episodes_path_length_in_the_max_norm():
    """Σ_t max_i |a[t, i]| over the xyz channels, per episode (the gripper channel ignored), in units of the bound:
    closed-form sums, episodes never mixed, a bad ``episode_ends`` named."""
    from hipolicy_jax.data.windowing import steps_at_bound

    a = np.zeros((7, 4))
    a[:3, :3] = [[1.0, -0.5, 0.0], [0.2, 0.3, -0.4], [0.0, 0.0, 0.0]]  # episode 1: 1 + 0.4 + 0
    a[3:, :3] = [[-1.0, 1.0, 1.0], [0.5, 0.5, 0.5], [0.1, 0.0, 0.0], [0.0, 0.0, -0.9]]  # 1 + 0.5 + 0.1 + 0.9
    a[:, 3] = 1.0  # the gripper moves every step: not a displacement channel
    np.testing.assert_allclose(steps_at_bound(a, np.array([3, 7])), [1.4, 2.5])
    np.testing.assert_allclose(steps_at_bound(a, np.array([3, 7]), bound=0.5), [2.8, 5.0])
    np.testing.assert_allclose(steps_at_bound(a, np.array([7])), [3.9])
    with pytest.raises(ValueError, match="episode_ends"):
        steps_at_bound(a, np.array([3, 8]))


def test_delta_segment_coverage_closed_form():
    """A stride-s segment of displacement actions moves 1/s of the demo's way at constant speed; on a ramp
    a_i = i the ratio is Σ_k (f+ks) / Σ_{i<sL} (f+i); windows never cross an episode end; still windows drop."""
    from hipolicy_jax.data.windowing import delta_segment_coverage

    chunk = ChunkConfig(strides=(1, 2, 3))  # L_c 8, δ 1
    const = np.tile(np.array([[1.0, 0.0, 0.0, 0.7]]), (100, 1))
    cov = delta_segment_coverage(const, np.array([100]), chunk)
    for s in (1, 2, 3):
        assert cov[s].shape == (100 - 8 * s,)  # first frames δ .. 100 - 8 s
        np.testing.assert_allclose(cov[s], 1.0 / s)

    ramp = np.arange(60, dtype=np.float64)[:, None]
    cov = delta_segment_coverage(ramp, np.array([60]), chunk, dims=(0,))
    f = np.arange(1, 60 - 24 + 1)  # stride 3: first action index of each window
    expected = (8 * f + 3 * 28) / (24 * f + 24 * 23 / 2)
    np.testing.assert_allclose(cov[3], expected)

    # two episodes moving in opposite directions: a window across the boundary would mix them
    two = np.concatenate([np.ones((40, 3)), -np.ones((30, 3))])
    cov = delta_segment_coverage(two, np.array([40, 70]), chunk)
    assert cov[3].shape == ((40 - 24) + (30 - 24),)
    np.testing.assert_allclose(cov[3], 1 / 3)
    assert delta_segment_coverage(np.zeros((50, 3)), np.array([50]), chunk)[2].shape == (0,)
    with pytest.raises(ValueError, match="episode_ends"):
        delta_segment_coverage(const, np.array([101]), chunk)
