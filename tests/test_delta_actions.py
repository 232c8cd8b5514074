"""Delta actions at longer strides (issue 62): declared action kinds, summed-delta segments, per-segment statistics.

The toy demo moves at a constant velocity: its xyz deltas are the same every frame and its gripper (absolute)
counts frames, so a stride-s segment's expected actions have a closed form.
"""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import zarr

from hipolicy_jax.campaigns.campaign import training_key
from hipolicy_jax.checkpoint import config_from_dict, config_to_dict
from hipolicy_jax.config import ChunkConfig, InferenceConfig, PolicyConfig, replace
from hipolicy_jax.data import Normalizer, ReplayBuffer, SequenceDataset, sample_indices
from hipolicy_jax.data.importers import import_dp_zarr, robomimic_action_kinds
from hipolicy_jax.data.validation import DataValidationError
from hipolicy_jax.data.windowing import resolve_chunk_kinds, segment_actions
from hipolicy_jax.deploy.backend import make_metadata
from hipolicy_jax.envs import external
from hipolicy_jax.envs.demos import check_buffer_fits_env, demo_buffer

KINDS = ("delta", "delta", "delta", "absolute")
VELOCITY = np.array([0.01, -0.02, 0.005], np.float32)
# strides (1, 2, 3) -> segment order (3, 2, 1); L_c = 4, δ = 1
CHUNK = ChunkConfig(strides=(1, 2, 3), obs_horizon=2, chunk_len=4, action_offset=1, action_kinds=KINDS)


def toy_buffer(lengths=(40,), velocities=None, kinds=KINDS) -> ReplayBuffer:
    """Episodes at constant velocity: action[t] = (v, t) with v the episode's xyz delta, t its frame (gripper)."""
    episodes = []
    for i, n in enumerate(lengths):
        v = VELOCITY if velocities is None else velocities[i]
        action = np.concatenate([np.broadcast_to(v, (n, 3)), np.arange(n, dtype=np.float32)[:, None]], axis=1)
        episodes.append({"action": action.astype(np.float32), "state": np.zeros((n, 2), np.float32)})
    return ReplayBuffer.from_episodes(episodes, action_kinds=kinds)


def segment(x, chunk, stride):
    """The (..., L_c, A) segment of stride ``stride`` of chunks (..., M*L_c, A)."""
    m = chunk.segment_strides.index(stride)
    return x[..., m * chunk.chunk_len:(m + 1) * chunk.chunk_len, :]


# ------------------------------------------------------------------------------------------------- closed form
def test_stride_s_segment_of_a_constant_velocity_demo_carries_s_steps_of_motion():
    buf = toy_buffer()
    current = np.array([0, 5, 12])  # windows that lie inside the 40-frame episode
    chunks = segment_actions(buf.data["action"], buf.episode_ends, current, CHUNK, KINDS)
    assert chunks.shape == (3, CHUNK.horizon, 4) and chunks.dtype == np.float32
    one = segment(chunks, CHUNK, 1)
    for s in (1, 2, 3):
        seg = segment(chunks, CHUNK, s)
        expected = (s * VELOCITY.astype(np.float64)).astype(np.float32)
        np.testing.assert_array_equal(seg[..., :3], np.broadcast_to(expected, seg[..., :3].shape))
        # the absolute gripper keeps today's sampling: a[t+δ+i·s]
        frames = current[:, None] + 1 + s * np.arange(CHUNK.chunk_len)[None, :]
        np.testing.assert_array_equal(seg[..., 3], frames.astype(np.float32))
    np.testing.assert_allclose(segment(chunks, CHUNK, 3)[..., :3], 3 * one[..., :3], rtol=1e-6)
    # a stride-3 segment moves as far as the demo does over its 3·L_c frames
    np.testing.assert_allclose(segment(chunks, CHUNK, 3)[0, :, :3].sum(0), 3 * CHUNK.chunk_len * VELOCITY, rtol=1e-6)


def test_dataset_batches_unnormalise_to_summed_deltas():
    buf = toy_buffer(lengths=(40, 30), velocities=[VELOCITY, 2 * VELOCITY])
    ds = SequenceDataset(buf, CHUNK, obs_keys=("state",))
    assert ds.normalizer.per_segment("action")
    idx = np.arange(len(ds))
    action = ds.normalizer.unnormalize("action", ds.get_batch(idx)["action"])
    expected = segment_actions(buf.data["action"], buf.episode_ends, ds.current, CHUNK, KINDS)
    np.testing.assert_allclose(action, expected, rtol=1e-5, atol=1e-6)
    assert ds.get_batch(idx)["action"].min() >= -1 - 1e-6 and ds.get_batch(idx)["action"].max() <= 1 + 1e-6


# ----------------------------------------------------------------------------------------------- episode edges
def test_padding_past_the_episode_end_is_zero_motion_and_absolute_repeats_the_last():
    buf = toy_buffer(lengths=(10, 10))  # episode 0: frames 0..9, episode 1: frames 10..19
    chunk = ChunkConfig(strides=(1, 3), obs_horizon=1, chunk_len=4, action_offset=1, action_kinds=KINDS)
    t = np.array([6])  # stride-3 blocks from frame 7: {7,8,9}, {10,11,12}, {13..15}, {16..18}
    chunks = segment_actions(buf.data["action"], buf.episode_ends, t, chunk, KINDS)
    s3, s1 = segment(chunks, chunk, 3)[0], segment(chunks, chunk, 1)[0]
    v = VELOCITY.astype(np.float64)
    np.testing.assert_array_equal(s3[:, :3], np.stack([3 * v, 0 * v, 0 * v, 0 * v]).astype(np.float32))
    # stride 1: frames 7, 8, 9 inside, frame 10 past the end contributes nothing (not a repeat of the last delta)
    np.testing.assert_array_equal(s1[:, :3], np.stack([v, v, v, 0 * v]).astype(np.float32))
    # absolute dims: clamped to the episode's last frame (9), never the next episode's frames
    np.testing.assert_array_equal(s3[:, 3], [7, 9, 9, 9])
    np.testing.assert_array_equal(s1[:, 3], [7, 8, 9, 9])
    # a block cut by the end sums only its frames inside
    t = np.array([5])  # stride-3 blocks from 6: {6,7,8}, {9,10,11} → only frame 9 inside
    cut = segment(segment_actions(buf.data["action"], buf.episode_ends, t, chunk, KINDS), chunk, 3)[0]
    np.testing.assert_array_equal(cut[:2, :3], np.stack([3 * v, v]).astype(np.float32))


def test_padding_before_the_episode_start_is_zero_motion_for_a_negative_offset():
    buf = toy_buffer(lengths=(8, 8))
    chunk = ChunkConfig(strides=(1,), obs_horizon=3, chunk_len=4, action_offset=-2, action_kinds=KINDS)
    chunks = segment_actions(buf.data["action"], buf.episode_ends, np.array([8]), chunk, KINDS)[0]  # frames 6..9
    v = VELOCITY.astype(np.float32)
    np.testing.assert_array_equal(chunks[:, :3], np.stack([0 * v, 0 * v, v, v]))
    np.testing.assert_array_equal(chunks[:, 3], [0, 0, 0, 1])  # episode 1's first frame repeated, frames 0, 1


def test_per_segment_normalisation_at_episode_edges_round_trips():
    buf = toy_buffer(lengths=(9, 7))  # short episodes: most windows are padded
    ds = SequenceDataset(buf, CHUNK, obs_keys=("state",))
    raw = segment_actions(buf.data["action"], buf.episode_ends, ds.current, CHUNK, KINDS)
    stats = ds.normalizer.stats["action"]
    assert stats["min"].shape == (CHUNK.horizon, 4)
    # padded blocks bring zero motion into every stride's range: each segment's min of the delta dims is 0 there
    # (VELOCITY[0] > 0) and its max is s·v
    for s in (1, 2, 3):
        np.testing.assert_allclose(segment(stats["max"], CHUNK, s)[:, 0], s * VELOCITY[0], rtol=1e-6)
        np.testing.assert_array_equal(segment(stats["min"], CHUNK, s)[:, 0], 0.0)
    back = ds.normalizer.unnormalize("action", ds.normalizer.normalize("action", raw))
    np.testing.assert_allclose(back, raw, rtol=1e-6, atol=1e-7)


# ------------------------------------------------------------------------------------------ per-segment stats
def test_stride_3_segment_range_is_three_times_stride_1():
    rng = np.random.default_rng(0)
    velocities = rng.uniform(0.5, 1.0, size=(6, 3)).astype(np.float32) * np.array([1, -1, 1], np.float32)
    buf = toy_buffer(lengths=(40,) * 6, velocities=velocities)
    chunk = replace(CHUNK, **{"chunk_len": 4})
    norm = SequenceDataset(buf, chunk, obs_keys=("state",)).normalizer
    lo, hi = norm.stats["action"]["min"], norm.stats["action"]["max"]
    span = {s: (segment(hi, chunk, s) - segment(lo, chunk, s))[0] for s in (1, 3)}
    # with the zero-motion padding in every range: stride s spans [0, s·max v] (or [s·min v, 0])
    np.testing.assert_allclose(span[3][:3], 3 * span[1][:3], rtol=1e-5)
    # the absolute gripper's range barely changes with the stride (the frame count, sampled)
    assert abs(span[3][3] - span[1][3]) <= 3
    x = segment_actions(buf.data["action"], buf.episode_ends, np.arange(0, 200, 7), chunk, KINDS)
    y = norm.normalize("action", jnp.asarray(x))  # jax arrays too, as the sampler calls it
    np.testing.assert_allclose(np.asarray(norm.unnormalize("action", y)), x, rtol=1e-6, atol=1e-7)
    assert np.abs(np.asarray(y)).max() <= 1 + 1e-6  # every stride fills its own [-1, 1]


def test_per_segment_normaliser_saves_and_checks_its_input_shape():
    norm = SequenceDataset(toy_buffer(), CHUNK, obs_keys=("state",)).normalizer
    again = Normalizer.from_dict(norm.to_dict())
    assert again.per_segment("action") and not again.per_segment("state")
    x = np.ones((2, 5, CHUNK.horizon, 4), np.float32)  # (B, N, M·L_c, A) as the sampler has them
    np.testing.assert_array_equal(again.unnormalize("action", x), norm.unnormalize("action", x))
    with pytest.raises(ValueError, match=r"'action' has per-segment statistics for chunks \(\.\.\., M\*L_c, A\) = "
                                         r"\(\.\.\., 12, 4\), got shape \(7, 4\)"):
        norm.normalize("action", np.ones((7, 4), np.float32))
    # a per-feature normaliser (one saved before per-segment statistics existed) is refused by a delta chunk
    flat = Normalizer.fit({"action": np.ones((4, 4)), "state": np.ones((4, 2))})
    with pytest.raises(ValueError, match=r"normalizer: its action statistics are per feature \(A,\), "
                                         r"chunk.action_kinds=.* needs them per segment"):
        SequenceDataset(toy_buffer(), CHUNK, obs_keys=("state",), normalizer=flat)


# ------------------------------------------------------------------------------------------- all absolute = today
def test_all_absolute_kinds_reproduce_todays_windows_and_normalisation_exactly():
    rng = np.random.default_rng(3)
    lengths = (12, 5, 9)
    episodes = [{"action": rng.normal(size=(n, 4)).astype(np.float32),
                 "state": rng.normal(size=(n, 3)).astype(np.float32)} for n in lengths]
    chunk = ChunkConfig(strides=(1, 2, 3), obs_horizon=2, chunk_len=4)
    legacy = ReplayBuffer.from_episodes(episodes)
    declared = ReplayBuffer.from_episodes(episodes, action_kinds=("absolute",) * 4)
    explicit = replace(chunk, action_kinds=("absolute",) * 4)
    current, _, act_idx = sample_indices(legacy.episode_ends, chunk)
    # today's construction, written out: frames normalised with frame statistics, gathered at act_idx
    today = Normalizer.fit({"action": legacy.data["action"], "state": legacy.data["state"]})
    today_actions = today.normalize("action", legacy.data["action"])[act_idx]
    np.testing.assert_array_equal(
        segment_actions(legacy.data["action"], legacy.episode_ends, current, chunk, ("absolute",) * 4),
        legacy.data["action"][act_idx])
    for buf, ch in ((legacy, chunk), (declared, chunk), (declared, explicit)):
        ds = SequenceDataset(buf, ch, obs_keys=("state",))
        assert not ds.normalizer.per_segment("action")
        for key in ("action", "state"):
            for name in ("scale", "offset", "min", "max"):
                np.testing.assert_array_equal(ds.normalizer.stats[key][name], today.stats[key][name])
        np.testing.assert_array_equal(ds.get_batch(np.arange(len(ds)))["action"], today_actions)


# ------------------------------------------------------------------------------------------------ the buffer
def test_buffer_records_action_kinds_as_a_root_attribute(tmp_path):
    toy_buffer().save(tmp_path / "delta.zarr")
    assert zarr.open_group(str(tmp_path / "delta.zarr"), mode="r").attrs["action_kinds"] == list(KINDS)
    assert ReplayBuffer.load(tmp_path / "delta.zarr").action_kinds == KINDS
    toy_buffer(kinds=None).save(tmp_path / "legacy.zarr")
    assert "action_kinds" not in zarr.open_group(str(tmp_path / "legacy.zarr"), mode="r").attrs
    assert ReplayBuffer.load(tmp_path / "legacy.zarr").action_kinds is None
    # a buffer the Meta-World bridge wrote (root attribute set directly) reads the same
    root = zarr.open_group(str(tmp_path / "legacy.zarr"), mode="r+")
    root.attrs["action_kinds"] = ["delta", "delta", "delta", "absolute"]
    assert ReplayBuffer.load(tmp_path / "legacy.zarr").action_kinds == KINDS
    root.attrs["action_kinds"] = ["delta", "velocity", "delta", "absolute"]
    with pytest.raises(ValueError, match=r"legacy.zarr: action_kinds: each kind must be 'absolute' or 'delta', "
                                         r"got 'velocity'"):
        ReplayBuffer.load(tmp_path / "legacy.zarr")


def test_importer_reads_kinds_from_the_source_or_takes_them_as_an_argument(tmp_path):
    src = tmp_path / "src.zarr"
    toy_buffer().save(src)  # this project's buffer: records its kinds
    buf, summary = import_dp_zarr(src)
    assert buf.action_kinds == KINDS and summary.action_kinds == KINDS
    assert "action kinds: delta delta delta absolute" in summary.format()
    with pytest.raises(DataValidationError, match=r"says its action kinds are \['delta', 'delta', 'delta', "
                                                  r"'absolute'\], action_kinds gives \['absolute'"):
        import_dp_zarr(src, action_kinds=("absolute",))
    plain = tmp_path / "plain.zarr"
    toy_buffer(kinds=None).save(plain)
    buf, summary = import_dp_zarr(plain)
    assert buf.action_kinds is None and "action kinds: unknown" in summary.format()
    assert import_dp_zarr(plain, action_kinds=["absolute"])[0].action_kinds == ("absolute",) * 4  # one for all
    assert import_dp_zarr(plain, action_kinds=KINDS)[1].to_dict()["action_kinds"] == list(KINDS)
    # the command line's flag records them in the written buffer
    from experiments import import_data
    import_data.main(["dp-zarr", str(plain), str(tmp_path / "out.zarr"), "--action-kinds", *KINDS])
    assert ReplayBuffer.load(tmp_path / "out.zarr").action_kinds == KINDS


def test_robomimic_control_delta_says_the_kinds():
    args = {"env_kwargs": {"controller_configs": {"type": "OSC_POSE", "control_delta": True}}}
    assert robomimic_action_kinds(json.dumps(args), 7) == ("delta",) * 6 + ("absolute",)
    args["env_kwargs"]["controller_configs"]["control_delta"] = False
    assert robomimic_action_kinds(json.dumps(args), 7) == ("absolute",) * 7
    assert robomimic_action_kinds(None, 7) is None and robomimic_action_kinds("{not json", 7) is None


# ------------------------------------------------------------------------------------------------ bad inputs
def test_bad_kinds_are_one_line_errors_naming_the_field(tmp_path):
    with pytest.raises(ValueError, match=r"^chunk.action_kinds: each kind must be 'absolute' or 'delta', got "
                                         r"'velocity' in \['delta', 'velocity'\]$"):
        ChunkConfig(action_kinds=("delta", "velocity"))
    with pytest.raises(ValueError, match=r"^chunk.action_kinds: expected a sequence"):
        ChunkConfig(action_kinds="delta")
    # wrong length against the action dimension
    with pytest.raises(ValueError, match=r"^chunk.action_kinds: expected 4 kinds \(one per action dimension\), "
                                         r"got 3"):
        SequenceDataset(toy_buffer(), replace(CHUNK, action_kinds=KINDS[:3]), obs_keys=("state",))
    toy_buffer(kinds=None).save(tmp_path / "p.zarr")
    with pytest.raises(DataValidationError, match=r"^action_kinds: expected 4 kinds \(one per action dimension\), "
                                                  r"got 2"):
        import_dp_zarr(tmp_path / "p.zarr", action_kinds=KINDS[:2])
    # the buffer's kinds disagree with the config's
    msg = (r"^chunk.action_kinds: the policy's actions are \['absolute', 'absolute', 'absolute', 'absolute'\], but "
           r"the buffer has action_kinds \['delta', 'delta', 'delta', 'absolute'\]; pass --policy.chunk.action-kinds "
           r"delta delta delta absolute")
    with pytest.raises(ValueError, match=msg):
        SequenceDataset(toy_buffer(), replace(CHUNK, action_kinds=None), obs_keys=("state",))
    with pytest.raises(ValueError, match=r"^chunk.action_kinds: the policy's actions are \['absolute'.*but "
                                         r"the buffer data/x.zarr has action_kinds \['delta'"):
        resolve_chunk_kinds(replace(CHUNK, action_kinds=("absolute",) * 4), KINDS, None, 4, "the buffer data/x.zarr")
    # the buffer's kinds disagree with its task's
    with pytest.raises(ValueError, match=r"^data: the buffer data/x.zarr has action_kinds \['delta', .*its task acts "
                                         r"with \['absolute'"):
        resolve_chunk_kinds(replace(CHUNK, action_kinds=None), KINDS, ("absolute",) * 4, 4, "the buffer data/x.zarr")


def test_a_delta_dataset_imported_without_kinds_is_refused_where_strides_need_them(tmp_path):
    toy_buffer(kinds=None).save(tmp_path / "teleop.zarr")
    buf, _ = import_dp_zarr(tmp_path / "teleop.zarr")  # the source does not say, no argument given
    with pytest.raises(ValueError, match=r"^chunk.action_kinds: the buffer teleop.zarr does not record whether its 4 "
                                         r"action dimensions are 'absolute' or 'delta'.*strides \(1, 2, 3\) need it; "
                                         r"pass --policy.chunk.action-kinds"):
        resolve_chunk_kinds(replace(CHUNK, action_kinds=None), buf.action_kinds, None, 4, "the buffer teleop.zarr")
    # a single stride does not need them; a declared chunk, or the buffer's task, says them
    one = replace(CHUNK, strides=(1,), action_kinds=None)
    assert resolve_chunk_kinds(one, None, None, 4, "b") == one
    assert resolve_chunk_kinds(CHUNK, None, None, 4, "b") == CHUNK
    assert resolve_chunk_kinds(replace(CHUNK, action_kinds=None), None, KINDS, 4, "b").action_kinds == KINDS


# ---------------------------------------------------------------------------------------- identity and tasks
def test_runs_without_kinds_keep_their_identity():
    cfg = PolicyConfig()
    old = config_to_dict(cfg)
    del old["chunk"]["action_kinds"]  # a run recorded before the field existed
    assert config_from_dict(PolicyConfig, old) == cfg
    key = training_key(old, 64)
    assert key == training_key(config_to_dict(cfg), 64) and "action_kinds" not in key
    # all-absolute demos leave a None chunk as it is (the run's identity unchanged); deltas are stored in it
    none = replace(CHUNK, action_kinds=None)
    assert resolve_chunk_kinds(none, ("absolute",) * 4, ("absolute",) * 4, 4, "b") is none
    assert resolve_chunk_kinds(none, KINDS, KINDS, 4, "b") == CHUNK


def test_tasks_declare_their_kinds_and_demos_must_match():
    assert external.make("metaworld:assembly").action_kinds == KINDS
    assert external.make("metaworld-target:assembly").action_kinds == ("absolute",) * 4
    from hipolicy_jax import envs
    env = envs.make("press_button")
    assert env.action_kinds == ("absolute",) * env.action_dim
    episodes = [{"action": np.zeros((5, 4), np.float32), "state": np.zeros((5, env.state_dim), np.float32)}]
    assert demo_buffer("press_button", episodes).action_kinds == env.action_kinds  # what collection records
    demos = ReplayBuffer.from_episodes(episodes, action_kinds=KINDS)
    with pytest.raises(ValueError, match=r"d.zarr: records action_kinds \['delta', 'delta', 'delta', 'absolute'\], "
                                         r"the press_button task acts with \['absolute'"):
        check_buffer_fits_env(demos, env, "d.zarr")


def test_policy_for_demos_takes_the_buffers_kinds_and_matches_its_config():
    from hipolicy_jax.runs.train import RunConfig, policy_for_demos, same_policy
    cfg = RunConfig(task="metaworld:assembly", data="data/x.zarr",
                    policy=PolicyConfig(chunk=replace(CHUNK, action_kinds=None)))
    env = cfg.task_spec()
    legacy = toy_buffer(kinds=None)  # a bridge buffer collected before the attribute: the suite's kinds
    trained = policy_for_demos(cfg, legacy, env)
    assert trained.chunk.action_kinds == KINDS
    assert same_policy(trained, cfg.policy) and not same_policy(trained, replace(cfg.policy, **{"chunk.chunk_len": 8}))
    target = RunConfig(task="metaworld-target:assembly", data="data/x.zarr", policy=cfg.policy)
    assert policy_for_demos(target, toy_buffer(kinds=("absolute",) * 4), target.task_spec()) == cfg.policy


def test_server_metadata_lists_the_action_kinds():
    meta = dict(task="metaworld:assembly", action_dim=4, inference=InferenceConfig(), thresholds=[0.0, 1.0, 2.0, 3.0],
                thresholds_source="test", obs={})
    assert make_metadata(cfg=PolicyConfig(chunk=CHUNK), **meta)["action_kinds"] == list(KINDS)
    assert make_metadata(cfg=PolicyConfig(), **meta)["action_kinds"] == ["absolute"] * 4


def test_sampler_unnormalises_with_per_segment_statistics():
    """``sample``'s chunks are the network's output unnormalised segment by segment (summed deltas)."""
    from hipolicy_jax.sampling import sample

    class Constant:  # a "network" whose denoised output is 0.5 everywhere (sample prediction)
        def apply(self, params, *args, method=None):
            return args[0] * 0 + 0.5 if method is not None and method.__name__ == "denoise" else args[0]

        def encode(self, obs):
            return obs

        def denoise(self, x, t, cond):
            return x

    norm = SequenceDataset(toy_buffer(), CHUNK, obs_keys=("state",)).normalizer
    cfg = PolicyConfig(chunk=CHUNK, diffusion=replace(PolicyConfig().diffusion, prediction_type="sample"))
    res = sample({}, norm, {"state": jnp.zeros((1, 3, 2, 2))}, jax.random.key(0), net=Constant(), cfg=cfg,
                 action_dim=4, inference=InferenceConfig(num_samples=2, sampler="ddim", num_steps=2),
                 obs_normalized=True)
    expected = np.asarray(norm.unnormalize("action", np.full((CHUNK.horizon, 4), 0.5, np.float32)))
    np.testing.assert_allclose(np.asarray(res.chunks[0, 0]), expected, rtol=1e-5, atol=1e-6)
    assert not np.allclose(expected[:CHUNK.chunk_len], expected[-CHUNK.chunk_len:])  # stride 3 ≠ stride 1
