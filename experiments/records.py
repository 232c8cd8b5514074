"""Check and upgrade the campaign's run records (``results/runs``): one trained network per record.

    python -m experiments.records check                 # every record holds one network; exit 1 naming those that don't
    python -m experiments.records upgrade               # version-1 records → version 2, networks read from git history

``upgrade`` stamps every evaluation of a version-1 record with the final training loss of the network it was made
on (the record's ``training.final_loss`` in the first commit that held the evaluation) and moves the evaluations of
an earlier training to ``superseded``; the campaign then makes them again on one network
(``hipolicy_jax/runs/records.py``).
"""

from __future__ import annotations

import dataclasses
import glob
import os
from typing import Literal

import tyro

from hipolicy_jax.runs import records as rec_lib
from hipolicy_jax.runs.store import read_json, write_json


@dataclasses.dataclass(frozen=True)
class RecordsArgs:
    action: tyro.conf.Positional[Literal["check", "upgrade"]]
    records: str = "results/runs"  # <records>/<budget>/<task>/<obs>/<variant>/seed<k>.json


def record_files(root: str) -> list[str]:
    if not os.path.isdir(root):
        raise FileNotFoundError(f"records: {root} is not a directory of run records")
    return sorted(glob.glob(os.path.join(root, "**", "seed*.json"), recursive=True))


def main(args: RecordsArgs) -> int:
    paths = record_files(args.records)
    if args.action == "upgrade":
        changed = 0
        for path in paths:
            record = read_json(path)
            if record.get("version", 1) >= rec_lib.RECORD_VERSION:
                continue
            new = rec_lib.upgrade_v1(record, rec_lib.git_first_losses(path))
            write_json(path, new)
            changed += 1
            if new.get("superseded"):
                moved = sum(len(s["evaluations"]) for s in new["superseded"])
                print(f"{path}: {moved} evaluation(s) of an earlier training moved to 'superseded'; "
                      f"{len(new['evaluations'])} kept")
        print(f"upgraded {changed} of {len(paths)} records to version {rec_lib.RECORD_VERSION}")
        return 0
    bad = 0
    for path in paths:
        problems = rec_lib.problems(read_json(path))
        for p in problems:
            print(f"{path}: {p}")
        bad += bool(problems)
    print(f"{len(paths) - bad} of {len(paths)} records hold one network" + (f"; {bad} do not" if bad else ""))
    return 1 if bad else 0


if __name__ == "__main__":
    try:
        raise SystemExit(main(tyro.cli(RecordsArgs, description=__doc__)))
    except (ValueError, FileNotFoundError) as e:
        raise SystemExit(f"error: {e}")
