"""Importers (Diffusion Policy zarr, robomimic hdf5, LeRobot v2.x and v3.0) and their validation, on small files made
here and on a LeRobot v3.0 dataset written by the real library (tests/fixtures/lerobot_v3)."""

import json
import os
import shutil
from fractions import Fraction

import numpy as np
import pytest
import zarr

from experiments import import_data
from hipolicy_jax.data import ReplayBuffer, SequenceDataset
from hipolicy_jax.data.importers import (import_dp_zarr, import_lerobot, import_robomimic, parse_key_map,
                                         robomimic_demo_names)
from hipolicy_jax.data.validation import DataValidationError, check_source_episode_ends


# ------------------------------------------------------------------------------------------------------ builders
def dp_episodes(lengths, seed=0):
    """Episodes of DP Push-T's layout: state (T, 2), action (T, 2), img (T, 8, 8, 3) float32 in [0, 255],
    keypoint (T, 9, 2); action[:, 0] holds the episode index."""
    rng = np.random.default_rng(seed)
    eps = []
    for i, n in enumerate(lengths):
        eps.append({"state": rng.normal(size=(n, 2)).astype(np.float32),
                    "action": np.stack([np.full(n, i, np.float32), np.arange(n, dtype=np.float32)], axis=1),
                    "img": rng.integers(0, 256, size=(n, 8, 8, 3)).astype(np.float32),
                    "keypoint": rng.normal(size=(n, 9, 2)).astype(np.float32)})
    return eps


def write_dp_zarr(path, episodes, episode_ends=None, zarr_format=2):
    """Write a DP ReplayBuffer (zarr format 2 as DP's own files) with ``data/<key>`` and ``meta/episode_ends``."""
    root = zarr.open_group(str(path), mode="w", zarr_format=zarr_format)
    data = root.create_group("data")
    for key in episodes[0]:
        arr = np.concatenate([ep[key] for ep in episodes]) if episodes else np.zeros((0,))
        data.create_array(key, data=arr, chunks=(max(1, min(16, arr.shape[0])),) + arr.shape[1:])
    ends = np.cumsum([len(ep["action"]) for ep in episodes]) if episode_ends is None else episode_ends
    root.create_group("meta").create_array("episode_ends", data=np.asarray(ends, dtype=np.int64))
    return str(path)


def write_robomimic(path, lengths, image=True, order=None):
    """robomimic hdf5: data/demo_<i>/{actions, obs/...}; actions[:, 0] holds the demo index i."""
    h5py = pytest.importorskip("h5py")
    rng = np.random.default_rng(1)
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        for i in (order if order is not None else range(len(lengths))):
            n = lengths[i]
            demo = data.create_group(f"demo_{i}")
            demo.attrs["num_samples"] = n
            demo.create_dataset("actions", data=np.concatenate([np.full((n, 1), i), rng.normal(size=(n, 6))], 1))
            demo.create_dataset("rewards", data=np.zeros(n))
            obs = demo.create_group("obs")
            obs.create_dataset("robot0_eef_pos", data=np.full((n, 3), float(i)))
            obs.create_dataset("robot0_eef_quat", data=rng.normal(size=(n, 4)))
            obs.create_dataset("robot0_gripper_qpos", data=np.full((n, 2), -float(i)))
            obs.create_dataset("object", data=rng.normal(size=(n, 10)))
            if image:
                obs.create_dataset("agentview_image", data=rng.integers(0, 256, (n, 8, 8, 3), dtype=np.uint8))
        f.create_group("mask")
    return str(path)


def write_mp4(path, frames, fps):
    """Encode ``(n, H, W, 3) uint8`` frames to an H.264 mp4 with PyAV, one frame every 1/fps seconds."""
    av = pytest.importorskip("av")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with av.open(path, "w") as container:
        stream = container.add_stream("libx264", rate=fps)
        stream.height, stream.width = frames.shape[1:3]
        stream.pix_fmt = "yuv420p"
        for i, img in enumerate(frames):
            frame = av.VideoFrame.from_ndarray(img, format="rgb24")
            frame.pts, frame.time_base = i, Fraction(1, fps)
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def video_frames(ep, n):
    """Flat-coloured 16x16 frames whose grey level encodes (episode, frame): robust to lossy encoding."""
    levels = (40 * ep + 10 * np.arange(n)) % 250
    return np.broadcast_to(levels[:, None, None, None], (n, 16, 16, 3)).astype(np.uint8).copy()


def write_lerobot(root, lengths, fps=10, video=False, version="v2.1", edit_table=None, extra_features=None):
    """A LeRobot v2 folder: meta/info.json, meta/episodes.jsonl, data/chunk-000/episode_XXXXXX.parquet, videos."""
    pa = pytest.importorskip("pyarrow")
    pq = pytest.importorskip("pyarrow.parquet")
    features = {"observation.state": {"dtype": "float32", "shape": [3], "names": None},
                "action": {"dtype": "float32", "shape": [2], "names": None},
                "episode_index": {"dtype": "int64", "shape": [1], "names": None},
                "frame_index": {"dtype": "int64", "shape": [1], "names": None},
                "timestamp": {"dtype": "float32", "shape": [1], "names": None},
                "next.reward": {"dtype": "float32", "shape": [1], "names": None}}
    if video:
        features["observation.image"] = {"dtype": "video", "shape": [16, 16, 3],
                                         "names": ["height", "width", "channel"]}
    features.update(extra_features or {})
    info = {"codebase_version": version, "fps": fps, "total_episodes": len(lengths), "chunks_size": 1000,
            "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
            "video_path": "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4",
            "features": features}
    os.makedirs(os.path.join(root, "meta"), exist_ok=True)
    with open(os.path.join(root, "meta", "info.json"), "w") as fh:
        json.dump(info, fh)
    with open(os.path.join(root, "meta", "episodes.jsonl"), "w") as fh:
        for ep, n in enumerate(lengths):
            fh.write(json.dumps({"episode_index": ep, "tasks": ["push"], "length": n}) + "\n")
    for ep, n in enumerate(lengths):
        cols = {"observation.state": pa.array(list(np.full((n, 3), ep, np.float32)), pa.list_(pa.float32())),
                "action": pa.array(list(np.stack([np.full(n, ep), np.arange(n)], 1).astype(np.float32)),
                                   pa.list_(pa.float32())),
                "episode_index": pa.array(np.full(n, ep, np.int64)),
                "frame_index": pa.array(np.arange(n, dtype=np.int64)),
                "timestamp": pa.array((np.arange(n) / fps).astype(np.float32)),
                "next.reward": pa.array(np.zeros(n, np.float32))}
        if edit_table is not None:
            cols = edit_table(ep, cols)
        path = os.path.join(root, "data", "chunk-000", f"episode_{ep:06d}.parquet")
        os.makedirs(os.path.dirname(path), exist_ok=True)
        pq.write_table(pa.table(cols), path)
        if video:
            write_mp4(os.path.join(root, "videos", "chunk-000", "observation.image", f"episode_{ep:06d}.mp4"),
                      video_frames(ep, n), fps)
    return str(root)


# ------------------------------------------------------------------------------------------------------ key maps
def test_parse_key_map():
    assert parse_key_map(["state=robot0_eef_pos, robot0_gripper_qpos", "image=agentview_image"]) == {
        "state": ("robot0_eef_pos", "robot0_gripper_qpos"), "image": ("agentview_image",)}
    for bad in (["state"], ["=x"], ["state="], ["state=a,"]):
        with pytest.raises(ValueError, match="expected 'obs_key=src_key'"):
            parse_key_map(bad)
    with pytest.raises(ValueError, match="mapped twice"):
        parse_key_map(["state=a", "state=b"])


def test_robomimic_demo_names_numeric_order():
    demos, other = robomimic_demo_names(["demo_10", "demo_9", "demo_0", "demo_1", "mask", "demo_x"])
    assert demos == ["demo_0", "demo_1", "demo_9", "demo_10"] and other == ["demo_x", "mask"]


# ------------------------------------------------------------------------------------------------------- DP zarr
def test_dp_zarr_default_map_converts_float_images(tmp_path):
    eps = dp_episodes([30, 25])
    buf, summary = import_dp_zarr(write_dp_zarr(tmp_path / "pusht.zarr", eps), min_length=5)
    assert set(buf.data) == {"state", "action", "image", "keypoint"}
    np.testing.assert_array_equal(buf.episode_ends, [30, 55])
    assert buf.data["image"].dtype == np.uint8 and buf.data["image"].shape == (55, 8, 8, 3)
    np.testing.assert_array_equal(buf.data["image"], np.concatenate([e["img"] for e in eps]).astype(np.uint8))
    np.testing.assert_array_equal(buf.data["state"], np.concatenate([e["state"] for e in eps]))
    assert summary.key_map["image"] == ("img",) and summary.keys["image"] == ((8, 8, 3), "uint8")
    assert [r.length for r in summary.kept] == [30, 25] and not summary.dropped
    assert any("float32 pixels in [0, 255] rounded to uint8" in n for n in summary.notes)
    assert "img renamed image" in summary.notes


def test_dp_zarr_unit_range_images_and_zarr3_and_zip(tmp_path):
    eps = dp_episodes([12])
    eps[0]["img"] /= 255.0
    buf, summary = import_dp_zarr(write_dp_zarr(tmp_path / "a.zarr", eps, zarr_format=3))
    np.testing.assert_array_equal(buf.data["image"], np.rint(eps[0]["img"] * 255).astype(np.uint8))
    assert any("[0, 1] scaled by 255" in n for n in summary.notes)
    zipped = shutil.make_archive(str(tmp_path / "b.zarr"), "zip", write_dp_zarr(tmp_path / "b.zarr", eps))
    buf_zip, _ = import_dp_zarr(zipped)
    np.testing.assert_array_equal(buf_zip.data["image"], buf.data["image"])


def test_dp_zarr_key_map_and_unused_keys(tmp_path):
    eps = dp_episodes([10, 10])
    buf, summary = import_dp_zarr(write_dp_zarr(tmp_path / "p.zarr", eps),
                                  key_map=parse_key_map(["state=state,action", "image=img"]))
    assert set(buf.data) == {"action", "state", "image"}  # action added from its default source
    assert buf.data["state"].shape == (20, 4)
    assert "source keys not imported: keypoint" in summary.notes


def test_dp_zarr_drops_short_and_empty_episodes_and_reports_them(tmp_path):
    eps = dp_episodes([30, 4, 25])
    ends = [30, 30, 34, 59]  # episode 1 is empty (equal ends), episode 2 has 4 frames
    buf, summary = import_dp_zarr(write_dp_zarr(tmp_path / "p.zarr", eps, episode_ends=ends), min_length=23)
    np.testing.assert_array_equal(buf.episode_ends, [30, 55])
    np.testing.assert_array_equal(buf.data["action"][30:, 0], 2)  # the third episode follows the first
    assert [(r.name, r.length, r.reason) for r in summary.dropped] == [
        ("episode 1", 0, "empty (0 frames)"), ("episode 2", 4, "too short: 4 frames < min_length 23")]
    text = summary.format()
    assert "dropped: 2 episodes (min_length 23)" in text and "episode 2: too short: 4 frames < min_length 23" in text
    with pytest.raises(DataValidationError, match="no episode left to import, all 4 dropped"):
        import_dp_zarr(tmp_path / "p.zarr", min_length=100)


@pytest.mark.parametrize("case, match", [
    ("missing_key", r"p\.zarr: data: missing key 'velocity' \(mapped to 'state'\); available keys"),
    ("decreasing_ends", r"meta/episode_ends: expected non-decreasing cumulative ends, but episode 1 ends at 10, "
                        r"before the previous end 20"),
    ("last_end", r"meta/episode_ends: expected the last end to equal the number of frames 40, got 39"),
    ("length_mismatch", r"data/state is float32 \(39, 2\), expected 40 frames \(the length of data/action\); "
                        r"obs/action length mismatch"),
    ("nan", r"episode 1 \(frames 20:40\): key 'state' \(from data/state\) contains nan at frame 3 "
            r"of 20 \(1 non-finite frames\); expected finite values"),
    ("inf_image", r"episode 0 .*key 'image' \(from data/img\) contains NaN or Inf at frame 2"),
    ("wrong_rank", r"key 'state' \(from data/state\) expected rank 2 \(T, D\), got rank 1 float32 \(20,\)"),
    ("image_channels", r"key 'image' \(from data/img\) expected shape \(T, H, W, 3\) uint8, got uint8 \(20, 8, 8, 4\)"),
    ("image_range", r"key 'image' \(from data/img\) has pixel values in \[-3, 255\], expected \[0, 255\]"),
])
def test_dp_zarr_errors_name_file_key_expected_and_actual(tmp_path, case, match):
    eps = dp_episodes([20, 20])
    key_map = None
    ends = None
    if case == "missing_key":
        key_map = {"state": ("velocity",)}
    elif case == "decreasing_ends":
        ends = [20, 10, 40]
    elif case == "last_end":
        ends = [20, 39]
    elif case == "length_mismatch":
        eps[1]["state"] = eps[1]["state"][:-1]
    elif case == "nan":
        eps[1]["state"][3, 1] = np.nan
    elif case == "inf_image":
        eps[0]["img"][2, 0, 0, 0] = np.inf
    elif case == "wrong_rank":
        for ep in eps:
            ep["state"] = ep["state"][:, 0]
    elif case == "image_channels":
        for ep in eps:
            ep["img"] = np.concatenate([ep["img"], ep["img"][..., :1]], axis=-1)
    elif case == "image_range":
        eps[0]["img"][0, 0, 0, 0] = -3
    path = write_dp_zarr(tmp_path / "p.zarr", eps, episode_ends=ends)
    with pytest.raises(DataValidationError, match=match) as info:
        import_dp_zarr(path, key_map=key_map)
    assert "p.zarr" in str(info.value)


def test_dp_zarr_missing_groups(tmp_path):
    root = zarr.open_group(str(tmp_path / "x.zarr"), mode="w")
    root.create_group("data").create_array("action", data=np.zeros((4, 2)))
    with pytest.raises(DataValidationError, match=r"x\.zarr: missing key 'meta/episode_ends'"):
        import_dp_zarr(tmp_path / "x.zarr")
    with pytest.raises(FileNotFoundError, match="no such Diffusion Policy zarr dataset"):
        import_dp_zarr(tmp_path / "nothing.zarr")


def test_source_episode_ends_checks():
    np.testing.assert_array_equal(check_source_episode_ends([2, 2, 5], 5, "f: ends"), [2, 0, 3])
    with pytest.raises(DataValidationError, match="f: ends: expected an integer dtype"):
        check_source_episode_ends(np.array([2.0, 5.0]), 5, "f: ends")
    with pytest.raises(DataValidationError, match=r"f: ends: expected a 1-D array \(E,\)"):
        check_source_episode_ends(np.array([[5]]), 5, "f: ends")


# ----------------------------------------------------------------------------------------------------- robomimic
def test_robomimic_numeric_demo_order_key_map_and_images(tmp_path):
    lengths = [30 + i for i in range(11)]
    path = write_robomimic(tmp_path / "lift.hdf5", lengths, order=[10, 2, 0, 9, 1, 3, 4, 5, 6, 7, 8])
    buf, summary = import_robomimic(path, key_map=parse_key_map(
        ["state=robot0_eef_pos,robot0_gripper_qpos", "image=agentview_image"]))
    assert [r.name for r in summary.kept] == [f"demo_{i}" for i in range(11)]  # demo_10 after demo_9
    np.testing.assert_array_equal(buf.episode_lengths(), lengths)
    for i in range(11):
        ep = buf.get_episode(i)
        np.testing.assert_array_equal(ep["action"][:, 0], i)
        np.testing.assert_array_equal(ep["state"], np.concatenate([np.full((lengths[i], 3), i),
                                                                   np.full((lengths[i], 2), -i)], axis=1))
    assert buf.data["action"].shape == (sum(lengths), 7) and buf.data["image"].dtype == np.uint8
    assert summary.keys == {"action": ((7,), "float64"), "state": ((5,), "float64"), "image": ((8, 8, 3), "uint8")}
    assert any(n.startswith("source keys not imported: object, rewards, robot0_eef_quat") for n in summary.notes)


def test_robomimic_default_map_and_short_demo(tmp_path):
    path = write_robomimic(tmp_path / "d.hdf5", [40, 10, 40], image=False)
    buf, summary = import_robomimic(path, min_length=23)
    assert summary.key_map == {"action": ("actions",),
                               "state": ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")}
    assert buf.num_episodes == 2 and buf.data["state"].shape == (80, 9)
    assert [(r.name, r.reason) for r in summary.dropped] == [("demo_1", "too short: 10 frames < min_length 23")]


def test_robomimic_errors(tmp_path):
    h5py = pytest.importorskip("h5py")
    path = write_robomimic(tmp_path / "d.hdf5", [30, 30])
    with pytest.raises(DataValidationError, match=r"d\.hdf5: data/demo_0: missing key 'obs/robot0_joint_pos' "
                                                  r"\(mapped to 'state'\)"):
        import_robomimic(path, key_map={"state": ("robot0_joint_pos",)})
    with pytest.raises(DataValidationError, match=r"cannot concatenate sources of key 'state' along the last axis: "
                                                  r"'obs/robot0_eef_pos' is float64 \(30, 3\) but "
                                                  r"'obs/agentview_image' is uint8 \(30, 8, 8, 3\)"):
        import_robomimic(path, key_map={"state": ("robot0_eef_pos", "agentview_image")})
    with h5py.File(path, "a") as f:
        del f["data/demo_1/obs/robot0_eef_pos"]
        f["data/demo_1/obs/robot0_eef_pos"] = np.zeros((29, 3))
        f["data/demo_0"].attrs["num_samples"] = 31
    with pytest.raises(DataValidationError, match=r"data/demo_0: attribute num_samples is 31 but key 'action'"):
        import_robomimic(path)
    with h5py.File(path, "a") as f:
        f["data/demo_0"].attrs["num_samples"] = 30
    with pytest.raises(DataValidationError, match=r"d\.hdf5: data/demo_1: key 'state' \(from obs/robot0_eef_pos\) "
                                                  r"has 29 frames but key 'action' \(from actions\) has 30.*"
                                                  r"obs/action length mismatch"):
        import_robomimic(path, key_map={"state": ("robot0_eef_pos",)})


def test_robomimic_not_robomimic(tmp_path):
    h5py = pytest.importorskip("h5py")
    with h5py.File(tmp_path / "x.hdf5", "w") as f:
        f.create_dataset("actions", data=np.zeros((3, 2)))
    with pytest.raises(DataValidationError, match=r"x\.hdf5: missing group 'data'"):
        import_robomimic(tmp_path / "x.hdf5")


# ------------------------------------------------------------------------------------------------------- LeRobot
def test_lerobot_parquet_episodes(tmp_path):
    root = write_lerobot(tmp_path / "ds", [30, 5, 25])
    buf, summary = import_lerobot(root, min_length=10)
    assert summary.key_map == {"state": ("observation.state",), "action": ("action",)}
    np.testing.assert_array_equal(buf.episode_ends, [30, 55])
    np.testing.assert_array_equal(buf.data["state"][30:], 2)  # episode 2 follows episode 0
    np.testing.assert_array_equal(buf.data["action"][:30, 1], np.arange(30))
    assert buf.data["state"].dtype == np.float32
    assert [(r.name, r.reason) for r in summary.dropped] == [("episode 1", "too short: 5 frames < min_length 10")]
    assert "source keys not imported: next.reward" in summary.notes
    buf2, _ = import_lerobot(root, key_map=parse_key_map(["state=observation.state,next.reward"]))
    assert buf2.data["state"].shape == (60, 4)


def test_lerobot_video_frames_match_timestamps(tmp_path):
    pytest.importorskip("av")
    root = write_lerobot(tmp_path / "ds", [12, 9], video=True)
    buf, summary = import_lerobot(root)
    assert summary.key_map["image"] == ("observation.image",)
    assert buf.data["image"].shape == (21, 16, 16, 3) and buf.data["image"].dtype == np.uint8
    for ep, n in enumerate([12, 9]):
        got = buf.get_episode(ep)["image"].reshape(n, -1).mean(axis=1)
        np.testing.assert_allclose(got, video_frames(ep, n)[:, 0, 0, 0], atol=3)
    # A video shorter than its episode's timestamps is an error naming the file.
    write_mp4(os.path.join(root, "videos", "chunk-000", "observation.image", "episode_000001.mp4"),
              video_frames(1, 4), 10)
    with pytest.raises(DataValidationError,
                       match=r"episode_000001\.mp4: no video frame within 0\.0500s of frame 4's timestamp 0\.4000s"):
        import_lerobot(root)
    # Without the video files the default map leaves the camera out and says so.
    shutil.rmtree(os.path.join(root, "videos"))
    buf, summary = import_lerobot(root)
    assert "image" not in buf.data
    assert any(n.startswith("video feature observation.image not imported") for n in summary.notes)
    with pytest.raises(DataValidationError, match=r"missing video file .*episode_000000\.mp4"):
        import_lerobot(root, key_map={"image": ("observation.image",)})


def test_lerobot_png_image_feature(tmp_path):
    import pyarrow as pa
    iio = pytest.importorskip("imageio.v3")

    def add_images(ep, cols):
        n = len(cols["action"])
        png = [iio.imwrite("<bytes>", video_frames(ep, n)[i], extension=".png") for i in range(n)]
        cols["observation.image"] = pa.array([{"bytes": b, "path": f"frame_{i}.png"} for i, b in enumerate(png)])
        return cols

    root = write_lerobot(tmp_path / "ds", [12, 9], edit_table=add_images, extra_features={
        "observation.image": {"dtype": "image", "shape": [16, 16, 3], "names": ["height", "width", "channel"]}})
    buf, summary = import_lerobot(root)
    assert summary.key_map["image"] == ("observation.image",)
    np.testing.assert_array_equal(buf.data["image"], np.concatenate([video_frames(0, 12), video_frames(1, 9)]))


def _bad_frame_index(ep, cols):
    import pyarrow as pa
    if ep == 1:
        idx = np.arange(len(cols["frame_index"]))
        idx[[3, 4]] = idx[[4, 3]]
        cols["frame_index"] = pa.array(idx)
    return cols


def _float64_action(ep, cols):
    import pyarrow as pa
    cols["action"] = pa.array([list(map(float, a)) for a in cols["action"].to_pylist()], pa.list_(pa.float64()))
    return cols


def _ragged_state(ep, cols):
    import pyarrow as pa
    rows = cols["observation.state"].to_pylist()
    rows[2] = rows[2][:2]
    cols["observation.state"] = pa.array(rows, pa.list_(pa.float32()))
    return cols


def _nan_action(ep, cols):
    import pyarrow as pa
    rows = cols["action"].to_pylist()
    rows[7][0] = float("inf")
    cols["action"] = pa.array(rows, pa.list_(pa.float32()))
    return cols


@pytest.mark.parametrize("edit, match", [
    (_bad_frame_index, r"episode_000001\.parquet: column 'frame_index' is not 0\.\.19 in order: row 3 holds 4, "
                       r"expected 3"),
    (_float64_action, r"episode_000000\.parquet: column 'action': dtype float64, expected float32 as declared in "
                      r"meta/info\.json"),
    (_ragged_state, r"column 'observation\.state': ragged lists of lengths \[2, 3\]"),
    (_nan_action, r"episode_000000\.parquet \(episode 0\): key 'action' contains inf at frame 7 of 20"),
])
def test_lerobot_errors(tmp_path, edit, match):
    root = write_lerobot(tmp_path / "ds", [20, 20], edit_table=edit)
    with pytest.raises(DataValidationError, match=match):
        import_lerobot(root)


def test_lerobot_metadata_errors(tmp_path):
    root = write_lerobot(tmp_path / "ds", [20, 20])
    with open(os.path.join(root, "meta", "episodes.jsonl"), "a") as fh:
        fh.write(json.dumps({"episode_index": 2, "length": 20}) + "\n")
    with pytest.raises(DataValidationError, match=r"episode_000002\.parquet: missing parquet file of episode 2"):
        import_lerobot(root)
    with pytest.raises(DataValidationError, match=r"info\.json: features: missing key 'observation\.wrist'"):
        import_lerobot(root, key_map={"image": ("observation.wrist",)})
    for version in ("v1.6", "v4.0", "v3.1"):
        other = write_lerobot(tmp_path / version, [20], version=version)
        with pytest.raises(DataValidationError, match=rf"info\.json: codebase_version '{version}' is not supported; "
                                                      r"supported versions: v2\.x \(v2\.0, v2\.1: .*\) and v3\.0"):
            import_lerobot(other)
    with pytest.raises(DataValidationError, match=r"meta/info\.json: missing"):
        import_lerobot(tmp_path)


# -------------------------------------------------------------------------------------------------- LeRobot v3.0
# Written by lerobot 0.4.4 itself (scripts/make_lerobot_v3_fixture.py): 5 episodes, data and videos in file-000
# (episodes 0-2) and file-001 (episodes 3-4), expected.npz holding the values the script recorded.
LEROBOT_V3 = os.path.join(os.path.dirname(__file__), "fixtures", "lerobot_v3")
V3_CAMERA = "observation.images.cam"
V3_EPISODES = os.path.join("meta", "episodes", "chunk-000")
V3_DATA = os.path.join("data", "chunk-000")


def v3_expected():
    with np.load(os.path.join(LEROBOT_V3, "expected.npz")) as f:
        return {k: f[k] for k in f.files}


def v3_copy(tmp_path):
    return shutil.copytree(LEROBOT_V3, tmp_path / "v3")


def edit_parquet(path, edit):
    """Rewrite a parquet file with ``edit(columns: dict[str, pyarrow.Array]) -> None`` applied in place."""
    pa = pytest.importorskip("pyarrow")
    pq = pytest.importorskip("pyarrow.parquet")
    table = pq.read_table(path)
    cols = {name: table.column(name).combine_chunks() for name in table.column_names}
    edit(cols)
    pq.write_table(pa.table(cols), path)


def set_values(cols, name, rows, values):
    import pyarrow as pa
    arr = cols[name].to_numpy(zero_copy_only=False).copy()
    arr[rows] = values
    cols[name] = pa.array(arr, type=cols[name].type)


def test_lerobot_v3_fixture_imports_what_lerobot_wrote():
    pytest.importorskip("av")
    expected = v3_expected()
    buf, summary = import_lerobot(LEROBOT_V3)
    assert summary.key_map == {"state": ("observation.state",), "action": ("action",), "image": (V3_CAMERA,)}
    assert [(r.name, r.length) for r in summary.kept] == [(f"episode {i}", n)
                                                          for i, n in enumerate(expected["lengths"])]
    assert not summary.dropped and "LeRobot v3.0: 5 episodes in 2 parquet files" in summary.notes
    np.testing.assert_array_equal(buf.episode_lengths(), [16, 12, 20, 9, 14])
    np.testing.assert_array_equal(buf.data["state"], expected["state"])  # float32, bit for bit
    np.testing.assert_array_equal(buf.data["action"], expected["action"])
    assert buf.data["state"].dtype == buf.data["action"].dtype == np.float32
    assert buf.data["image"].shape == (71, 32, 32, 3) and buf.data["image"].dtype == np.uint8
    # Flat AV1 frames: each frame's colour within 4 levels of what was recorded. Consecutive frames differ by 17
    # levels, so episodes 1-2 and 4, which start mid-file (from_timestamp 1.6, 2.8, 0.9 s), are matched frame for
    # frame.
    colours = buf.data["image"].reshape(71, -1, 3).astype(np.float64).mean(axis=1)
    np.testing.assert_allclose(colours, expected["rgb"], atol=4)
    assert summary.keys["image"] == ((32, 32, 3), "uint8")


def test_lerobot_v3_cli_import_then_train(tmp_path, capsys):
    """The fixture through ``experiments.import_data lerobot`` to a zarr, loaded back and trained a few steps with
    an image + state policy (tiny network)."""
    pytest.importorskip("av")
    from hipolicy_jax.config import ChunkConfig, EncoderConfig, ModelConfig, PolicyConfig, TrainConfig
    from hipolicy_jax.data.dataset import train_heldout_datasets
    from hipolicy_jax.trainer import fit

    dst = str(tmp_path / "v3.zarr")
    import_data.main(["lerobot", LEROBOT_V3, dst, "--min-length", "10"])
    out = capsys.readouterr().out
    assert "wrote 4 episodes (62 frames)" in out and "episode 3: too short: 9 frames < min_length 10" in out
    buf = ReplayBuffer.load(dst)
    expected = v3_expected()
    keep = np.concatenate([np.arange(0, 48), np.arange(57, 71)])  # episode 3 (frames 48:57) dropped
    np.testing.assert_array_equal(buf.data["state"], expected["state"][keep])
    np.testing.assert_array_equal(buf.episode_lengths(), [16, 12, 20, 14])

    cfg = PolicyConfig(chunk=ChunkConfig(strides=(1, 2), obs_horizon=2, chunk_len=4),
                       model=ModelConfig(size="tiny", fusion_heads=2),
                       encoder=EncoderConfig(obs_type="image", image_size=32, crop_size=28, image_channels=(8,),
                                             num_keypoints=4, image_out=16, state_hidden=(16,), state_out=8))
    train_ds, _ = train_heldout_datasets(buf, cfg.chunk, cfg.encoder.obs_keys, val_ratio=0.25, seed=0)
    batch = train_ds.get_batch(np.arange(2))
    assert batch["obs"]["image"].shape[-3:] == (32, 32, 3) and batch["action"].shape[-1] == 3
    train_cfg = TrainConfig(batch_size=8, num_steps=4, lr=1e-3, warmup_steps=1, log_every=2, ckpt_every=4)
    res = fit(cfg, train_cfg, train_ds, str(tmp_path / "run"), progress=False, tensorboard=False)
    assert len(res.losses) == 4 and np.isfinite(res.losses).all()

    # by default nothing is dropped: the 9-frame episode (shorter than the default chunk's 23-frame action span)
    # is imported and gives training windows like the others (one per frame with a next action)
    import_data.main(["lerobot", LEROBOT_V3, str(tmp_path / "all.zarr")])
    out = capsys.readouterr().out
    assert "wrote 5 episodes (71 frames)" in out and "too short" not in out
    full = ReplayBuffer.load(str(tmp_path / "all.zarr"))
    np.testing.assert_array_equal(full.data["state"], expected["state"])
    np.testing.assert_array_equal(full.episode_lengths(), [16, 12, 20, 9, 14])
    ds = SequenceDataset(full, ChunkConfig(), obs_keys=("state",))
    assert len(ds) == 71 - 5 and np.isin(np.arange(48, 56), ds.current).all()


def _v3_drop_episodes_file(root):
    os.remove(os.path.join(root, V3_EPISODES, "file-001.parquet"))


def _v3_no_episodes_dir(root):
    shutil.rmtree(os.path.join(root, "meta", "episodes"))


def _v3_range_past_file(root):  # episode 4 (rows 9:23 of file-001, 23 rows) moved 3 frames on
    edit_parquet(os.path.join(root, V3_EPISODES, "file-001.parquet"), lambda c: (
        set_values(c, "dataset_from_index", 1, 60), set_values(c, "dataset_to_index", 1, 74)))


def _v3_range_into_next_episode(root):  # episode 1 (rows 16:28) moved 2 frames into episode 2
    edit_parquet(os.path.join(root, V3_EPISODES, "file-000.parquet"), lambda c: (
        set_values(c, "dataset_from_index", 1, 18), set_values(c, "dataset_to_index", 1, 30)))


def _v3_length(root):
    edit_parquet(os.path.join(root, V3_EPISODES, "file-000.parquet"), lambda c: set_values(c, "length", 2, 19))


def _v3_frame_index(root):  # episode 1's frames 3 and 4 (rows 19, 20) swapped
    edit_parquet(os.path.join(root, V3_DATA, "file-000.parquet"),
                 lambda c: set_values(c, "frame_index", [19, 20], [4, 3]))


def _v3_timestamp(root):  # episode 4's frame 5 (row 14 of file-001) at the time of frame 4
    edit_parquet(os.path.join(root, V3_DATA, "file-001.parquet"), lambda c: set_values(c, "timestamp", 14, 0.4))


def _v3_global_index(root):  # episode 3's fourth frame (row 3 of file-001) numbered 99 instead of 51
    edit_parquet(os.path.join(root, V3_DATA, "file-001.parquet"), lambda c: set_values(c, "index", 3, 99))


def _v3_float64_action(root):
    import pyarrow as pa

    def edit(c):
        c["action"] = pa.array(c["action"].to_pylist(), pa.list_(pa.float64(), 3))
    edit_parquet(os.path.join(root, V3_DATA, "file-000.parquet"), edit)


def _v3_state_shape(root):
    path = os.path.join(root, "meta", "info.json")
    info = json.load(open(path))
    info["features"]["observation.state"]["shape"] = [5]
    json.dump(info, open(path, "w"))


def _v3_missing_video(root):
    os.remove(os.path.join(root, "videos", V3_CAMERA, "chunk-000", "file-001.mp4"))


def _v3_from_timestamp(root):  # episode 4 said to start at 1.5 s of a 2.3 s file: its frames 8.. are past the end
    edit_parquet(os.path.join(root, V3_EPISODES, "file-001.parquet"),
                 lambda c: set_values(c, f"videos/{V3_CAMERA}/from_timestamp", 1, 1.5))


def _v3_missing_data_file(root):
    os.remove(os.path.join(root, V3_DATA, "file-001.parquet"))


def _v3_version(root):
    path = os.path.join(root, "meta", "info.json")
    info = json.load(open(path))
    info["codebase_version"] = "v4.0"
    json.dump(info, open(path, "w"))


@pytest.mark.parametrize("edit, match", [
    (_v3_drop_episodes_file, r"meta/info\.json: total_episodes is 5, but .*meta/episodes lists 3 episodes "
                             r"\(chunk-000/file-000\.parquet\); expected every episode listed once"),
    (_v3_no_episodes_dir, r"meta/episodes: missing; expected the per-episode metadata "
                          r"meta/episodes/chunk-NNN/file-NNN\.parquet of a LeRobot v3\.0 dataset"),
    (_v3_range_past_file, r"meta/episodes/chunk-000/file-001\.parquet: episode 4: "
                          r"dataset_from_index:dataset_to_index 60:74 is rows 12:26 of .*data/chunk-000/"
                          r"file-001\.parquet, which holds 23 rows \(dataset frames 48:71\); expected the episode's "
                          r"frames inside its parquet file"),
    (_v3_range_into_next_episode, r"data/chunk-000/file-000\.parquet \(episode 1, rows 18:30\): column "
                                  r"'episode_index' holds \[1, 2\], expected only 1"),
    (_v3_length, r"meta/episodes/chunk-000/file-000\.parquet: episode 2: column 'length' is 19, expected 20 "
                 r"\(dataset_to_index 48 - dataset_from_index 28\)"),
    (_v3_frame_index, r"data/chunk-000/file-000\.parquet \(episode 1, rows 16:28\): column 'frame_index' is not "
                      r"0\.\.11 in order: row 19 holds 4, expected 3"),
    (_v3_timestamp, r"data/chunk-000/file-001\.parquet \(episode 4, rows 9:23\): column 'timestamp' must strictly "
                    r"increase: row 14 is 0\.400000s after 0\.400000s"),
    (_v3_global_index, r"data/chunk-000/file-001\.parquet \(episode 3, rows 0:9\): column 'index' is not the "
                       r"episode's dataset_from_index\.\.dataset_to_index - 1 = 48\.\.56: row 3 holds 99, expected 51"),
    (_v3_float64_action, r"data/chunk-000/file-000\.parquet \(episode 0, rows 0:16\): column 'action': dtype "
                         r"float64, expected float32 as declared in meta/info\.json"),
    (_v3_state_shape, r"data/chunk-000/file-000\.parquet \(episode 0, rows 0:16\): column 'observation\.state': "
                      r"frames of shape \(4,\), expected \(5,\) as declared in meta/info\.json"),
    (_v3_missing_video, r"data/chunk-000/file-001\.parquet \(episode 3, rows 0:9\): feature "
                        r"'observation\.images\.cam': missing video file .*videos/observation\.images\.cam/"
                        r"chunk-000/file-001\.mp4"),
    (_v3_from_timestamp, r"chunk-000/file-001\.mp4: no video frame within 0\.0500s of frame 8's timestamp "
                         r"0\.8000s \(\+ from_timestamp 1\.5000s = 2\.3000s in the file\) \(nearest "
                         r"2\.2000s; .*\) for .*file-001\.parquet \(episode 4, rows 9:23\)"),
    (_v3_missing_data_file, r"data/chunk-000/file-001\.parquet: missing parquet file of episodes \[3, 4\] "
                            r"\(data/chunk_index 0, data/file_index 1 in .*meta/episodes/chunk-000/"
                            r"file-001\.parquet"),
    (_v3_version, r"info\.json: codebase_version 'v4\.0' is not supported; supported versions: "
                 r"v2\.x .* and v3\.0"),
])
def test_lerobot_v3_errors_name_file_key_expected_and_actual(tmp_path, edit, match):
    pytest.importorskip("av")
    root = v3_copy(tmp_path)
    edit(str(root))
    with pytest.raises(DataValidationError, match=match):
        import_lerobot(root)


def test_lerobot_v3_camera_columns_are_read_only_for_an_imported_camera(tmp_path):
    pytest.importorskip("av")
    root = v3_copy(tmp_path)
    edit_parquet(os.path.join(root, V3_EPISODES, "file-001.parquet"),
                 lambda c: c.pop(f"videos/{V3_CAMERA}/from_timestamp"))
    with pytest.raises(DataValidationError, match=r"meta/episodes/chunk-000/file-001\.parquet: missing column "
                                                  r"'videos/observation\.images\.cam/from_timestamp' of video "
                                                  r"feature 'observation\.images\.cam'"):
        import_lerobot(root)
    buf, summary = import_lerobot(root, key_map={"state": ("observation.state",)})
    assert set(buf.data) == {"state", "action"} and buf.num_frames == 71
    assert "source keys not imported: observation.images.cam" in summary.notes


def test_lerobot_v3_cli_error_is_one_line(tmp_path, capsys):
    root = v3_copy(tmp_path)
    _v3_range_past_file(str(root))
    with pytest.raises(SystemExit) as e:
        import_data.main(["lerobot", str(root), str(tmp_path / "o.zarr")])
    err = capsys.readouterr().err
    assert e.value.code == 1 and err.startswith("error: ") and err.count("\n") == 1 and "Traceback" not in err
    assert "episode 4: dataset_from_index:dataset_to_index 60:74" in err and not (tmp_path / "o.zarr").exists()


# ----------------------------------------------------------------------------------------------------------- CLI
def test_cli_dry_run_writes_nothing_and_prints_summary(tmp_path, capsys):
    src = write_dp_zarr(tmp_path / "p.zarr", dp_episodes([30, 5]))
    dst = tmp_path / "out.zarr"
    summary = import_data.main(["dp-zarr", src, str(dst), "--key-map", "image=img", "state=state", "--dry-run"])
    out = capsys.readouterr().out
    assert not dst.exists() and "dry run: nothing written" in out
    # every episode is kept by default (training pads episode edges); --min-length drops by explicit choice
    assert "kept: 2 episodes, 35 frames" in out and "dropped: 0 episodes (min_length 1)" in out
    assert "image: (T, 8, 8, 3) uint8" in out and summary.num_frames == 35
    summary = import_data.main(["dp-zarr", src, "--key-map", "image=img", "state=state", "--dry-run",
                                "--min-length", "23"])
    out = capsys.readouterr().out
    assert "kept: 1 episodes, 30 frames" in out and "episode 1: too short: 5 frames < min_length 23" in out
    assert summary.num_frames == 30
    import_data.main(["dp-zarr", src, "--dry-run"])  # DST is optional with --dry-run


def test_cli_writes_loadable_buffer_and_respects_force(tmp_path, capsys):
    pytest.importorskip("h5py")
    src = write_robomimic(tmp_path / "d.hdf5", [25, 26])
    dst = str(tmp_path / "sub" / "out.zarr")
    report = str(tmp_path / "summary.json")
    import_data.main(["robomimic", src, dst, "--key-map", "state=robot0_eef_pos,robot0_gripper_qpos",
                      "--summary-json", report])
    assert "wrote 2 episodes (51 frames)" in capsys.readouterr().out
    buf = ReplayBuffer.load(dst)
    assert set(buf.data) == {"action", "state"} and buf.data["state"].shape == (51, 5)
    assert json.load(open(report))["kept"] == [{"name": "demo_0", "length": 25}, {"name": "demo_1", "length": 26}]
    with pytest.raises(SystemExit) as e:
        import_data.main(["robomimic", src, dst])
    assert e.value.code == 2 and "exists; pass --force" in capsys.readouterr().err
    import_data.main(["robomimic", src, dst, "--force", "--min-length", "26"])
    assert ReplayBuffer.load(dst).num_episodes == 1


def test_cli_errors(tmp_path, capsys):
    eps = dp_episodes([30, 30])
    eps[0]["action"][4, 0] = np.nan
    src = write_dp_zarr(tmp_path / "p.zarr", eps)
    with pytest.raises(SystemExit) as e:
        import_data.main(["dp-zarr", src, str(tmp_path / "o.zarr")])
    err = capsys.readouterr().err
    assert e.value.code == 1 and "key 'action' (from data/action) contains nan at frame 4" in err
    assert not (tmp_path / "o.zarr").exists()
    for argv in (["dp-zarr", src], ["dp-zarr", src, "o", "--key-map", "state"], ["dp-zarr", src, src],
                 ["dp-zarr", src, "o", "--min-length", "0"]):
        with pytest.raises(SystemExit) as e:
            import_data.main(argv)
        assert e.value.code == 2
