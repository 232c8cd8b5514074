"""Write the small LeRobot v3.0 dataset of tests/fixtures/lerobot_v3/ with the real ``lerobot`` library.

Made with lerobot 0.4.4 (``CODEBASE_VERSION = "v3.0"``) in a scratch venv that is not the project's (lerobot pulls in
torch, which the project never depends on):

    python3.12 -m venv /root/lerobot-venv && /root/lerobot-venv/bin/pip install lerobot==0.4.4
    rm -rf tests/fixtures/lerobot_v3 && HF_HUB_OFFLINE=1 /root/lerobot-venv/bin/python \\
        scripts/make_lerobot_v3_fixture.py tests/fixtures/lerobot_v3

What it writes, through ``LeRobotDataset.create`` / ``add_frame`` / ``save_episode`` / ``finalize`` only:

* 5 episodes at 10 fps, lengths ``LENGTHS``; features ``observation.state`` (float32, 4), ``action`` (float32, 3)
  and the camera ``observation.images.cam`` (video, 32x32 RGB, LeRobot's default codec libsvtav1).
* Recorded in two sessions, as ``lerobot-record --resume`` does: episodes 0-2, ``finalize()``, then the dataset is
  reopened and episodes 3-4 are added. LeRobot starts new files on resume, so the dataset has both v3.0 cases:
  several episodes in one parquet / mp4 file (``file-000``: episodes 0-2, the mp4 holding them one after another,
  ``from_timestamp`` 0, 1.6, 2.8 s) and episodes in a later file (``file-001``: episodes 3-4), for data, videos and
  ``meta/episodes`` alike.
* ``expected.npz`` beside the dataset (not part of LeRobot's layout): ``lengths``, ``state``, ``action`` (all
  frames, concatenated in episode order) and ``rgb`` (each frame's flat colour, (T, 3) uint8), what the importer
  must give back (``tests/test_importers.py``).

Values are deterministic (no randomness): frame ``i`` of episode ``e`` has global index ``g``;
``state = [e, i, sin(g / 3), cos(g / 5)]``, ``action = [e + i / 100, -i / 10, (g % 7) / 7]`` and every pixel the
colour ``(v, 255 - v, 40 * e + 20)`` with ``v = (11 + 17 * g) % 251``: flat frames survive lossy encoding, and
consecutive frames differ by 17 grey levels, so a frame matched at the wrong timestamp shows.
"""

from __future__ import annotations

import argparse
import os
import sys

os.environ.setdefault("HF_HUB_OFFLINE", "1")  # everything is local; never reach the hub

import numpy as np  # noqa: E402

FPS = 10
LENGTHS = (16, 12, 20, 9, 14)
FIRST_SESSION = 3  # episodes recorded before the dataset is closed and reopened
CAMERA = "observation.images.cam"
SIZE = 32
REPO_ID = "hipolicy/lerobot_v3_fixture"

FEATURES = {
    "observation.state": {"dtype": "float32", "shape": (4,), "names": ["episode", "frame", "sin", "cos"]},
    "action": {"dtype": "float32", "shape": (3,), "names": ["a0", "a1", "a2"]},
    CAMERA: {"dtype": "video", "shape": (SIZE, SIZE, 3), "names": ["height", "width", "channels"]},
}


def frame_values(episode: int, i: int, g: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(state (4,), action (3,), rgb (3,) uint8) of frame ``i`` of ``episode`` (global index ``g``)."""
    state = np.array([episode, i, np.sin(g / 3), np.cos(g / 5)], np.float32)
    action = np.array([episode + i / 100, -i / 10, (g % 7) / 7], np.float32)
    v = (11 + 17 * g) % 251
    rgb = np.array([v, 255 - v, 40 * episode + 20], np.uint8)
    return state, action, rgb


def record(dataset, episodes: range, first_global: int, expected: dict) -> int:
    g = first_global
    for e in episodes:
        for i in range(LENGTHS[e]):
            state, action, rgb = frame_values(e, i, g)
            image = np.broadcast_to(rgb, (SIZE, SIZE, 3)).copy()
            dataset.add_frame({"observation.state": state, "action": action, CAMERA: image, "task": "reach"})
            expected["state"].append(state)
            expected["action"].append(action)
            expected["rgb"].append(rgb)
            g += 1
        dataset.save_episode()
    return g


def main(argv=None) -> None:
    import lerobot
    from lerobot.datasets.lerobot_dataset import CODEBASE_VERSION, LeRobotDataset

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", help="dataset folder to create (must not exist)")
    args = p.parse_args(argv)
    if os.path.exists(args.out):
        sys.exit(f"{args.out} exists; remove it first")
    expected = {"state": [], "action": [], "rgb": []}

    ds = LeRobotDataset.create(REPO_ID, fps=FPS, features=FEATURES, root=args.out, use_videos=True)
    g = record(ds, range(FIRST_SESSION), 0, expected)
    ds.finalize()
    del ds

    ds = LeRobotDataset(REPO_ID, root=args.out)  # resume recording: LeRobot opens new data / video / meta files
    record(ds, range(FIRST_SESSION, len(LENGTHS)), g, expected)
    ds.finalize()

    np.savez(os.path.join(args.out, "expected.npz"), lengths=np.array(LENGTHS, np.int64),
             **{k: np.stack(v) for k, v in expected.items()})
    print(f"lerobot {lerobot.__version__} (CODEBASE_VERSION {CODEBASE_VERSION}): wrote {len(LENGTHS)} episodes, "
          f"{sum(LENGTHS)} frames to {args.out}")


if __name__ == "__main__":
    main()
