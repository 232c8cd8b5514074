"""Import an external demonstration dataset into the project's zarr ReplayBuffer layout.

    python -m experiments.import_data dp-zarr pusht_cchi_v7_replay.zarr data/pusht.zarr
    python -m experiments.import_data robomimic lift/ph/image.hdf5 data/lift.zarr \\
        --key-map state=robot0_eef_pos,robot0_gripper_qpos image=agentview_image
    python -m experiments.import_data lerobot ~/lerobot/pusht data/lerobot_pusht.zarr --dry-run

Formats: ``dp-zarr`` (Diffusion Policy zarr ReplayBuffer), ``robomimic`` (hdf5), ``lerobot`` (local LeRobot v2.x
or v3.0 folder; videos decoded with PyAV). ``--key-map obs_key=src_key[,src_key...]`` picks and renames keys (several
sources are concatenated along the last axis); without it each format's default map is used (see
``hipolicy_jax.data.importers``). Every episode is kept by default: training pads episode edges as Diffusion
Policy's sampler does (observation history repeats the first frame, actions repeat the last), so an episode of any
length trains. ``--min-length N`` drops (and lists in the printed summary) episodes shorter than N frames, as an
explicit choice; any other problem stops the import with an error naming the file, key and expected vs actual. ``--dry-run``
validates and prints the summary without writing. Refuses to overwrite DST unless ``--force``.
``--action-kinds absolute|delta ...`` (one for every action dimension, or one per dimension) records whether the
actions are absolute targets or deltas, where the source does not say (``hipolicy_jax.data.importers``): a delta
dimension trained at stride s sums s deltas per action.
Exit status: 0 on success, 1 on invalid data, 2 on bad arguments.
"""

from __future__ import annotations

import argparse
import os
import sys

from hipolicy_jax import jsonio
from hipolicy_jax.config import ACTION_KINDS, ChunkConfig
from hipolicy_jax.data.importers import FORMATS, ImportSummary, import_dataset, parse_key_map
from hipolicy_jax.data.validation import DataValidationError


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("format", choices=FORMATS, help="source format")
    p.add_argument("src", help="source dataset (zarr directory or .zip, hdf5 file, LeRobot folder)")
    p.add_argument("dst", nargs="?", default=None, help="destination zarr directory (optional with --dry-run)")
    p.add_argument("--key-map", nargs="+", default=None, metavar="OBS_KEY=SRC_KEY[,SRC_KEY...]",
                   help="project key = source key(s); several sources are concatenated along the last axis")
    p.add_argument("--min-length", type=int, default=1,
                   help="drop (and report) episodes with fewer frames (default: %(default)s, keep every episode: "
                        "training pads episode edges; e.g. ChunkConfig().action_span = "
                        f"{ChunkConfig().action_span} keeps only episodes that fill the longest stride's chunk)")
    p.add_argument("--action-kinds", nargs="+", default=None, choices=ACTION_KINDS, metavar="KIND",
                   help="absolute or delta: one for every action dimension, or one per dimension (default: what "
                        "the source says, else unknown)")
    p.add_argument("--dry-run", action="store_true", help="validate and print the summary without writing")
    p.add_argument("--force", action="store_true", help="overwrite an existing DST")
    p.add_argument("--summary-json", default=None, help="also write the summary as JSON to this path")
    args = p.parse_args(argv)
    if args.dst is None and not args.dry_run:
        p.error("DST is required unless --dry-run")
    if args.min_length < 1:
        p.error(f"--min-length: must be >= 1, got {args.min_length}")
    try:
        args.key_map = parse_key_map(args.key_map) if args.key_map else None
    except ValueError as e:
        p.error(str(e))
    if args.dst is not None and os.path.abspath(args.dst) == os.path.abspath(args.src):
        p.error(f"DST {args.dst} is the source; choose another path")
    return args


def main(argv=None) -> ImportSummary:
    """Run the CLI; returns the import summary (also printed)."""
    args = parse_args(argv)
    if args.dst is not None and not args.dry_run and os.path.lexists(args.dst) and not args.force:
        print(f"error: {args.dst} exists; pass --force to overwrite it", file=sys.stderr)
        raise SystemExit(2)
    try:
        buffer, summary = import_dataset(args.format, args.src, key_map=args.key_map, min_length=args.min_length,
                                         action_kinds=args.action_kinds)
    except (DataValidationError, FileNotFoundError, ImportError) as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(1) from e
    print(summary.format())
    if args.summary_json:
        with open(args.summary_json, "w") as fh:
            fh.write(jsonio.dumps(summary.to_dict(), indent=2) + "\n")
    if args.dry_run:
        print("dry run: nothing written")
    else:
        os.makedirs(os.path.dirname(os.path.abspath(args.dst)), exist_ok=True)
        buffer.save(args.dst, overwrite=args.force)
        print(f"wrote {buffer.num_episodes} episodes ({buffer.num_frames} frames) to {args.dst}")
    return summary


if __name__ == "__main__":
    main()
