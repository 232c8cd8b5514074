"""DemoSpeedup as a data stage (``hipolicy_jax.speedup``, ``experiments.speedup``): the kernel-density entropy against
its closed form, the segmentation and downsampling on synthetic entropies, the accelerated buffer's layout, episode
ends and delta actions, each bad input refused in one line, and one end-to-end run with a tiny trained proxy."""

import os

import numpy as np
import pytest
import zarr

from hipolicy_jax.checkpoint import LoadedPolicy
from hipolicy_jax.config import ChunkConfig, EncoderConfig, ModelConfig, PolicyConfig, TrainConfig
from hipolicy_jax.data.replay_buffer import ReplayBuffer
from hipolicy_jax.runs.store import Run
from hipolicy_jax.speedup import (CASUAL, PRECISE, SPEEDUP_ATTR, SpeedupConfig, accelerate, buffer_task,
                                  check_proxy_fits, kde_entropy, keep_indices, label_frames, retime_episode,
                                  saturated_fraction, segments, speedup_demos)
from hipolicy_jax.speedup.stage import write_buffer


# ------------------------------------------------------------------------------------------------- the estimator
def _closed_form(sigma: float, h: float, dim: int) -> float:
    """The estimator's N -> oo value for samples of N(0, sigma^2 I_dim): -E_x log E_y exp(-|x-y|^2 / 2h^2). (With
    sigma well above h the mean density falls towards the self term 1/N and a finite N reads lower.)"""
    return dim / 2 * np.log(1 + sigma ** 2 / h ** 2) + dim * sigma ** 2 / (2 * (h ** 2 + sigma ** 2))


@pytest.mark.parametrize("sigma,h,dim", [(0.1, 0.1, 2), (0.002, 0.002, 3), (0.0015, 0.002, 4), (0.001, 0.002, 1)])
def test_kde_entropy_matches_its_closed_form_on_gaussian_samples(sigma, h, dim):
    x = sigma * np.random.default_rng(0).standard_normal((1000, dim))
    assert kde_entropy(x, h) == pytest.approx(_closed_form(sigma, h, dim), abs=0.05)


def test_kde_entropy_orders_point_mass_narrow_and_wide_and_is_bounded_by_log_n():
    rng = np.random.default_rng(1)
    n, h = 10, 0.002
    point = np.full((n, 4), 0.3)
    narrow, wide = 0.001 * rng.standard_normal((n, 4)), 0.5 * rng.standard_normal((n, 4))
    h_point, h_narrow, h_wide = (kde_entropy(x, h) for x in (point, narrow, wide))
    assert h_point == pytest.approx(0.0, abs=1e-7)  # density 1 at every sample
    assert h_point < h_narrow < h_wide <= np.log(n) + 1e-9
    assert h_wide == pytest.approx(np.log(n), abs=1e-6)  # samples far apart: each sees only itself
    batched = kde_entropy(np.stack([point, narrow, wide]), h)  # (..., N, D) -> (...)
    np.testing.assert_allclose(batched, [h_point, h_narrow, h_wide])
    assert saturated_fraction(batched, n) == pytest.approx(1 / 3)  # only the wide one is at the ceiling log N
    with pytest.raises(ValueError, match=r"N >= 2"):
        kde_entropy(np.zeros((1, 4)), h)


# ---------------------------------------------------------------------------------- segmentation and downsampling
@pytest.mark.parametrize("precise_z,rate", [(0.0, 4), (0.5, 2)])
def test_a_constant_entropy_demo_is_downsampled_at_exactly_the_declared_rate(precise_z, rate):
    """A constant entropy z-scores to 0: one segment, casual (not below precise_z 0) or precise (below 0.5)."""
    cfg = SpeedupConfig(precise_z=precise_z, casual_prefix=0)
    length = 10 * rate + 1
    labels = label_frames(np.full(length, 1.7), cfg)
    assert segments(labels) == [(0, length, CASUAL if rate == 4 else PRECISE)]
    kept = keep_indices(labels, cfg)
    np.testing.assert_array_equal(kept, np.arange(0, length, rate))
    assert np.all(np.diff(kept) == cfg.rate(int(labels[0])))


def test_low_entropy_segment_kept_at_the_precise_rate_and_the_rest_at_the_casual_rate():
    cfg = SpeedupConfig(casual_prefix=0)
    h = np.r_[np.full(40, 2.0), np.full(20, 0.1), np.full(41, 2.0)]
    h = h + 0.01 * np.random.default_rng(0).standard_normal(h.size)
    labels = label_frames(h, cfg)
    assert segments(labels) == [(0, 40, CASUAL), (40, 60, PRECISE), (60, 101, CASUAL)]
    kept = keep_indices(labels, cfg)
    assert kept[0] == 0 and kept[-1] == 100
    np.testing.assert_array_equal(kept[kept <= 40], np.arange(0, 41, 4))  # casual x4 up to the precise segment
    np.testing.assert_array_equal(kept[(kept >= 40) & (kept <= 60)], np.arange(40, 61, 2))  # precise x2
    np.testing.assert_array_equal(kept[kept >= 60], np.arange(60, 101, 4))


def test_a_short_dip_is_noise_the_prefix_is_casual_and_casual_jumps_to_the_next_precise_frame():
    cfg = SpeedupConfig(casual_prefix=10, min_segment=5)
    h = np.full(60, 2.0)
    h[3:20] = 0.0  # starts inside the prefix
    h[40:43] = 0.0  # 3 frames: shorter than min_segment
    labels = label_frames(h, cfg)
    assert segments(labels) == [(0, 10, CASUAL), (10, 20, PRECISE), (20, 60, CASUAL)]
    # upstream's walk: a casual frame whose next casual_rate frames are not all casual jumps to the next precise one
    np.testing.assert_array_equal(keep_indices(np.array([1, 1, 0, 0, 0, 1, 1, 1, 1, 1, 0, 0]), cfg),
                                  [0, 2, 4, 6, 10, 11])
    assert keep_indices(np.array([CASUAL]), cfg).tolist() == [0]
    assert keep_indices(np.array([PRECISE, PRECISE]), cfg).tolist() == [0, 1]


@pytest.mark.parametrize("field,value", [("num_samples", 1), ("bandwidth", 0.0), ("casual_rate", 1),
                                         ("min_segment", 0), ("casual_prefix", -1)])
def test_config_refuses_bad_values_naming_the_field(field, value):
    with pytest.raises(ValueError, match=rf"^speedup\.{field}: ") as e:
        SpeedupConfig(**{field: value})
    assert "\n" not in str(e.value)


# ----------------------------------------------------------------------------------------- the accelerated buffer
def _buffer(lengths=(37, 23, 50), kinds=None, seed=0) -> ReplayBuffer:
    rng = np.random.default_rng(seed)
    episodes = []
    for n in lengths:
        episodes.append({"state": rng.standard_normal((n, 3)).astype(np.float32),
                         "action": rng.standard_normal((n, 4)).astype(np.float32),
                         "image": rng.integers(0, 255, (n, 6, 6, 3), dtype=np.uint8)})
    return ReplayBuffer.from_episodes(episodes, action_kinds=kinds)


def _entropy(buffer: ReplayBuffer, seed=0) -> np.ndarray:
    """Per frame: high, then a low stretch in the middle of every episode."""
    out = []
    for n in buffer.episode_lengths():
        h = np.full(n, 2.0)
        h[n // 3: 2 * n // 3] = 0.2
        out.append(h)
    return np.concatenate(out) + 0.01 * np.random.default_rng(seed).standard_normal(buffer.num_frames)


def test_accelerated_buffer_keeps_the_layout_and_every_episodes_first_and_last_frame(tmp_path):
    cfg = SpeedupConfig(casual_prefix=0)
    src = _buffer(kinds=("absolute",) * 4)
    acc, episodes = accelerate(src, _entropy(src), ("absolute",) * 4, cfg)
    assert acc.keys == src.keys and acc.num_episodes == src.num_episodes and acc.action_kinds == src.action_kinds
    for key in src.keys:
        assert acc.data[key].dtype == src.data[key].dtype and acc.data[key].shape[1:] == src.data[key].shape[1:]
    lengths = acc.episode_lengths()
    assert np.all(lengths < src.episode_lengths()) and np.all(lengths >= 2)
    np.testing.assert_array_equal(acc.episode_ends, np.cumsum(lengths))
    for e, info in enumerate(episodes):
        old, new, kept = src.get_episode(e), acc.get_episode(e), np.asarray(info["kept"])
        assert kept[0] == 0 and kept[-1] == info["original_length"] - 1 and kept.size == info["new_length"]
        for key in src.keys:  # absolute actions and observations: the kept frames'
            np.testing.assert_array_equal(new[key], old[key][kept])
        labels = label_frames(_entropy(src)[src.episode_slice(e)], cfg)
        assert [tuple(s[:3]) for s in info["segments"]] == segments(labels)
        assert all(rate == cfg.rate(label) for _, _, label, rate in info["segments"])
    # on disk: the same zarr layout, the source's attributes and the record
    path = str(tmp_path / "press_button_state_3_speedup.zarr")
    write_buffer(acc, path, {"action_kinds": list(src.action_kinds), "origin": "test", SPEEDUP_ATTR: {"task": "x"}})
    back = ReplayBuffer.load(path)
    assert sorted(back.keys) == sorted(acc.keys) and back.action_kinds == src.action_kinds
    np.testing.assert_array_equal(back.episode_ends, acc.episode_ends)
    assert sorted(os.listdir(path)) == ["data", "meta", "zarr.json"]
    attrs = dict(zarr.open_group(path, mode="r").attrs)
    assert attrs["origin"] == "test" and attrs[SPEEDUP_ATTR] == {"task": "x"}
    with pytest.raises(FileExistsError, match=r"^--out: .* already exists"):
        write_buffer(acc, path, {})


def test_delta_actions_are_the_sum_of_the_deltas_each_kept_frame_replaces():
    kinds = ("delta", "delta", "delta", "absolute")
    action = np.arange(40, dtype=np.float32).reshape(10, 4)
    episode = {"state": np.arange(10, dtype=np.float32)[:, None], "action": action}
    kept = np.array([0, 4, 6, 9])
    new = retime_episode(episode, kept, kinds)
    want = np.stack([action[0:4, :3].sum(0), action[4:6, :3].sum(0), action[6:9, :3].sum(0), action[9, :3]])
    np.testing.assert_array_equal(new["action"][:, :3], want)
    np.testing.assert_array_equal(new["action"][:, 3], action[kept, 3])  # the absolute gripper: the kept targets
    np.testing.assert_array_equal(new["state"], episode["state"][kept])
    assert episode["action"] is action and np.array_equal(action, np.arange(40).reshape(10, 4))  # source untouched
    # a whole buffer: every episode moves as far as its original did
    src = _buffer(kinds=kinds)
    acc, _ = accelerate(src, _entropy(src), kinds, SpeedupConfig(casual_prefix=0))
    for e in range(src.num_episodes):
        np.testing.assert_allclose(acc.get_episode(e)["action"][:, :3].sum(0),
                                   src.get_episode(e)["action"][:, :3].sum(0), rtol=1e-5, atol=1e-5)


# -------------------------------------------------------------------------------------------------- bad input
def _fake_proxy(task="press_button", action_dim=4, obs_type="state", state_dim=3, kinds=None) -> Run:
    cfg = PolicyConfig(chunk=ChunkConfig(strides=(1, 2), obs_horizon=2, chunk_len=4, action_kinds=kinds),
                       encoder=EncoderConfig(obs_type=obs_type), model=ModelConfig(size="tiny", fusion_heads=2))
    meta = {"task": task, "action_dim": action_dim, "obs_shapes": {"state": [state_dim]}, "data": "elsewhere.zarr"}
    return Run("runs/proxy", "runs/proxy/checkpoints", LoadedPolicy(cfg, None, None, None, meta, 10), task)


def _one_line(e) -> str:
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(("--proxy: ", "--data: ", "--out: ", "error: "))
    return msg


def test_a_proxy_of_another_task_action_size_observations_or_kinds_is_refused_in_one_line(tmp_path):
    buf = _buffer()
    path = "data/press_button_state_3.zarr"
    assert check_proxy_fits(buf, _fake_proxy(), path, "press_button") == ("absolute",) * 4
    with pytest.raises(ValueError) as e:
        check_proxy_fits(buf, _fake_proxy(task="stack_cubes"), path, "press_button")
    assert "trained on stack_cubes" in _one_line(e) and "holds press_button demos" in str(e.value)
    with pytest.raises(ValueError) as e:
        check_proxy_fits(buf, _fake_proxy(action_dim=7), path, None)
    assert "7-dim actions" in _one_line(e) and "holds 4-dim actions" in str(e.value)
    with pytest.raises(ValueError) as e:
        check_proxy_fits(buf, _fake_proxy(obs_type="pointcloud"), path, None)
    assert "lacks ['point_cloud']" in _one_line(e)
    with pytest.raises(ValueError) as e:
        check_proxy_fits(buf, _fake_proxy(state_dim=9), path, None)
    assert "state frames of shape (9,)" in _one_line(e) and "holds (3,)" in str(e.value)
    with pytest.raises(ValueError) as e:
        check_proxy_fits(_buffer(kinds=("delta",) * 3 + ("absolute",)), _fake_proxy(), path, None)
    assert "action_kinds ['absolute', 'absolute', 'absolute', 'absolute']" in _one_line(e)
    # where a buffer's task comes from: its attribute, its speedup record, its file name (the longest task prefix)
    assert buffer_task("x.zarr", {"task": "latch_door"}) == "latch_door"
    assert buffer_task("x.zarr", {SPEEDUP_ATTR: {"task": "stack_cubes"}}) == "stack_cubes"
    assert buffer_task("data/stack_cubes_state_50.zarr", {}) == "stack_cubes"
    assert buffer_task("data/mine.zarr", {}) is None
    assert buffer_task("data/metaworld_assembly_10.zarr", {}, known=("metaworld:assembly",)) == "metaworld:assembly"


def test_a_missing_buffer_and_an_existing_output_are_refused_in_one_line(tmp_path, capsys):
    from experiments.speedup import cli

    missing = str(tmp_path / "nowhere.zarr")
    with pytest.raises(FileNotFoundError) as e:
        speedup_demos(missing, _fake_proxy(), str(tmp_path / "out.zarr"))
    assert _one_line(e).startswith(f"--data: no replay buffer at {missing!r}")
    with pytest.raises(SystemExit) as e:
        cli(["--data", missing, "--proxy", "runs/none", "--out", str(tmp_path / "out.zarr"), "--no-progress"])
    assert str(e.value).startswith("error: --data: no replay buffer at") and "\n" not in str(e.value)
    src = str(tmp_path / "press_button_state_3.zarr")
    _buffer().save(src)
    with pytest.raises(SystemExit) as e:
        cli(["--data", src, "--proxy", "runs/none", "--out", src, "--no-progress"])
    assert str(e.value).startswith("error: --out: ") and "the source buffer" in str(e.value)
    with pytest.raises(SystemExit) as e:
        cli(["--data", src, "--proxy", str(tmp_path / "no_run"), "--out", str(tmp_path / "o.zarr"), "--no-progress"])
    assert str(e.value).startswith("error: --proxy: checkpoint: ") and "does not exist" in str(e.value)
    with pytest.raises(SystemExit) as e:
        cli(["--data", src, "--proxy", "runs/none", "--out", str(tmp_path / "o.zarr"), "--episode", "3"])
    assert str(e.value) == "error: --episode: the demo to plot, in [0, 3), got 3"
    with pytest.raises(SystemExit) as e:
        cli(["--data", src, "--proxy", "runs/none", "--out", str(tmp_path / "o.zarr"), "--speedup.num-samples", "1"])
    assert e.value.code == 2  # tyro's parse error, naming the field
    assert "speedup.num_samples: must be an integer >= 2" in " ".join(capsys.readouterr().err.split())


# ------------------------------------------------------------------------------------ end to end, a real proxy
@pytest.fixture(scope="module")
def proxy_run(tmp_path_factory):
    """A tiny policy trained for a few steps on a small synthetic buffer named as press_button demos."""
    from hipolicy_jax.data.dataset import SequenceDataset
    from hipolicy_jax.trainer import fit

    root = tmp_path_factory.mktemp("speedup")
    data = str(root / "press_button_state_3.zarr")
    buffer = _buffer(kinds=("absolute",) * 4)
    ReplayBuffer({k: v for k, v in buffer.data.items() if k != "image"}, buffer.episode_ends,
                 buffer.action_kinds).save(data)
    cfg = PolicyConfig(chunk=ChunkConfig(strides=(1, 2), obs_horizon=2, chunk_len=4),
                       model=ModelConfig(size="tiny", fusion_heads=2))
    dataset = SequenceDataset(ReplayBuffer.load(data), cfg.chunk, obs_keys=("state",))
    out = str(root / "proxy")
    fit(cfg, TrainConfig(batch_size=16, num_steps=6, warmup_steps=1, log_every=3, ckpt_every=6), dataset, out,
        meta_extra={"task": "press_button", "data": os.path.abspath(data), "val_ratio": 0.1}, progress=False,
        tensorboard=False)
    return data, out


def test_speedup_cli_end_to_end_with_a_trained_proxy(proxy_run, tmp_path, capsys):
    from experiments.speedup import cli

    data, proxy = proxy_run
    out = str(tmp_path / "press_button_state_3_speedup.zarr")
    result = cli(["--data", data, "--proxy", proxy, "--out", out, "--speedup.num-samples", "4",
                  "--speedup.casual-prefix", "0", "--batch-size", "32", "--episode", "1", "--no-progress"])
    src, acc = ReplayBuffer.load(data), ReplayBuffer.load(out)
    assert acc.keys == src.keys and acc.action_kinds == src.action_kinds and acc.num_episodes == src.num_episodes
    assert np.all(acc.episode_lengths() < src.episode_lengths())
    rec = dict(zarr.open_group(out, mode="r").attrs)[SPEEDUP_ATTR]
    assert rec["source"] == os.path.abspath(data) and rec["proxy"] == os.path.abspath(proxy)
    assert rec["task"] == "press_button" and rec["config"]["num_samples"] == 4 and rec["config"]["casual_prefix"] == 0
    assert rec["original_lengths"] == src.episode_lengths().tolist()
    assert rec["new_lengths"] == acc.episode_lengths().tolist() and rec["new_frames"] == acc.num_frames
    entropy = np.asarray(rec["entropy"])
    assert entropy.shape == (src.num_frames,) and np.all(np.isfinite(entropy))
    assert np.all(entropy >= -1e-6) and np.all(entropy <= np.log(4) + 1e-6)  # the estimator's range for N = 4
    assert rec["saturated_fraction"] == saturated_fraction(entropy, 4)
    for e in range(src.num_episodes):  # re-derivable from the record: labels from the entropies, kept frames
        labels = label_frames(entropy[src.episode_slice(e)], SpeedupConfig(num_samples=4, casual_prefix=0))
        kept = keep_indices(labels, SpeedupConfig(casual_prefix=0))
        assert rec["kept"][e] == kept.tolist()
        np.testing.assert_array_equal(acc.get_episode(e)["state"], src.get_episode(e)["state"][kept])
    np.testing.assert_array_equal(result.entropy, entropy)
    printed = capsys.readouterr().out
    assert f"original: {src.num_frames:6d} frames" in printed and f"accelerated: {acc.num_frames:6d} frames" in printed
    assert f"ceiling log N = {np.log(4):.3f}" in printed
    assert os.path.getsize(str(tmp_path / "press_button_state_3_speedup_entropy.png")) > 0
    # the same demos under another task's name: refused in one line before any sampling
    other = str(tmp_path / "stack_cubes_state_3.zarr")
    src.save(other)
    with pytest.raises(SystemExit) as e:
        cli(["--data", other, "--proxy", proxy, "--out", str(tmp_path / "o.zarr"), "--no-progress"])
    assert str(e.value).startswith("error: --proxy: ") and "trained on press_button" in str(e.value)
    assert "holds stack_cubes demos" in str(e.value) and "\n" not in str(e.value)
