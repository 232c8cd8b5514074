"""Damaged stored files end in one line naming the file, what is wrong and what to do — never a traceback, never
silently wrong numbers. Every case writes a real file with the project's own code (a run record with
``write_json``, a demo buffer with ``ReplayBuffer.save``) and then damages its bytes on disk: a JSON file cut short,
garbled or emptied; a zarr chunk overwritten, cut short, deleted or swapped for another; a ``zarr.json`` cut short,
edited or deleted. A campaign meeting one skips that job, goes on, and lists it at the end.
"""

from __future__ import annotations

import json
import os
import runpy
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zarr

from hipolicy_jax import jsonio
from hipolicy_jax.campaigns import tables
from hipolicy_jax.campaigns.budgets import DP
from hipolicy_jax.campaigns.report import changes_text
from hipolicy_jax.campaigns.campaign import (RECORD_VERSION, Campaign, Column, CostModel, Job, read_record,
                                             record_path, work_off)
from hipolicy_jax.checkpoint import config_to_dict
from hipolicy_jax.data.replay_buffer import BufferDamaged, ReplayBuffer, array_sha256
from hipolicy_jax.runs import cli
from hipolicy_jax.runs.store import write_json

HINT = "the buffer is damaged: delete it to collect it again (or import it again)"


def one_line(message: str, *parts: str) -> str:
    """``message`` is one line holding every one of ``parts``; → it."""
    assert "\n" not in message and "Traceback" not in message, message
    for part in parts:
        assert part in message, (part, message)
    return message


def cut(path: str | Path, keep: float = 0.5) -> None:
    """Truncate the file at ``path`` to ``keep`` of its bytes (a write cut off, a disk filled)."""
    size = os.path.getsize(path)
    with open(path, "r+b") as f:
        f.truncate(int(size * keep))


def overwrite(path: str | Path, offset: int, data: bytes) -> None:
    with open(path, "r+b") as f:
        f.seek(offset)
        f.write(data)


# ------------------------------------------------------------------------------------------------------- JSON
def _a_record(path: Path) -> str:
    net = {"params_sha256": "ab" * 32, "final_loss": 0.1}
    ev = {"settings": {"episodes": 2}, "success_rate": 0.5, "success": [True, False], "steps": [10, 20],
          "thresholds": [-float("inf"), -1.0, float("inf")], "network": net}
    return write_json(str(path), {"version": RECORD_VERSION, "budget": "smoke", "network": net,
                                  "training": {"steps": 10, "wall_time_s": 100.0, "cpu_cores": 1},
                                  "evaluations": {json.dumps({"episodes": 2}): ev}})


def test_a_json_file_cut_short_names_its_path_line_and_column(tmp_path):
    path = _a_record(tmp_path / "seed0.json")
    assert read_record(path)["version"] == RECORD_VERSION  # as written, it reads
    text = Path(path).read_text()
    cut(path)
    with pytest.raises(jsonio.DamagedFileError) as e:
        jsonio.load(path)
    lineno = text[:len(text) // 2].count("\n") + 1
    one_line(str(e.value), f"{path}: not valid JSON (", f"line {lineno}, column ",
             f"restore it from git (git checkout -- {path}) or delete it so that it is made again")
    assert e.value.path == path and isinstance(e.value, ValueError)
    # a run record says what deleting it does
    with pytest.raises(jsonio.DamagedFileError) as e:
        read_record(path)
    one_line(str(e.value), f"{path}: not valid JSON (", f"git checkout -- {path}",
             "delete it to redo that run's evaluations")


@pytest.mark.parametrize("damage, problem", [
    (lambda p: cut(p, 0.0), "not valid JSON (it is empty)"),
    (lambda p: overwrite(p, 0, b"\xff\xfe\x00garbage"), "not UTF-8 text (byte 0xff at offset 0)"),
    (lambda p: overwrite(p, 0, b"["), "not valid JSON (Expecting ',' delimiter: line 2, column "),  # { → [
    (lambda p: Path(p).write_text('["a list"]\n'), "holds a JSON array, expected a record (a JSON object)"),
])
def test_a_record_emptied_garbled_or_not_an_object_is_one_line(tmp_path, damage, problem):
    path = _a_record(tmp_path / "seed0.json")
    damage(path)
    with pytest.raises(jsonio.DamagedFileError) as e:
        read_record(path)
    one_line(str(e.value), f"{path}: ", problem, "delete it to redo that run's evaluations")


def test_a_json_write_never_leaves_half_a_file(tmp_path):
    """``jsonio.dump`` writes a temporary sibling and renames it into place: no partial file stays beside it."""
    path = _a_record(tmp_path / "seed0.json")
    _a_record(tmp_path / "seed0.json")
    assert os.listdir(tmp_path) == ["seed0.json"] and jsonio.load(path)["budget"] == "smoke"


def test_records_cli_on_a_damaged_record_ends_in_one_line(tmp_path):
    root = tmp_path / "records"
    good = _a_record(root / "smoke" / "t" / "state" / "dp" / "seed0.json")
    bad = _a_record(root / "smoke" / "t" / "state" / "dp" / "seed1.json")
    cut(bad)
    done = subprocess.run([sys.executable, "-m", "experiments.records", "check", "--records", str(root)],
                          capture_output=True, text=True, cwd=Path(__file__).parent.parent, timeout=300)
    assert done.returncode == 1 and done.stdout == ""
    one_line(done.stderr.strip(), f"error: {bad}: not valid JSON (", f"git checkout -- {bad}")
    assert done.stderr.count("\n") == 1 and good not in done.stderr


# ------------------------------------------------------------------------------------------------ demo buffers
def _buffer(path: Path, episodes: int = 3) -> tuple[str, ReplayBuffer]:
    rng = np.random.default_rng(0)
    buffer = ReplayBuffer.from_episodes([{"state": rng.normal(size=(20, 3)).astype(np.float32),
                                          "action": rng.normal(size=(20, 2)).astype(np.float32)}
                                         for _ in range(episodes)])
    buffer.save(path)
    return str(path), buffer


def test_a_saved_buffer_reads_back_checked(tmp_path):
    """``save`` stores each array's SHA-256 and writes every chunk with zstd's checksum; ``load`` verifies them."""
    path, buffer = _buffer(tmp_path / "demos.zarr")
    back = ReplayBuffer.load(path)
    assert all(np.array_equal(back.data[k], buffer.data[k]) for k in buffer.data)
    assert np.array_equal(back.episode_ends, buffer.episode_ends)
    meta = json.loads(Path(path, "data", "action", "zarr.json").read_text())
    assert len(meta["attributes"]["sha256"]) == 64
    assert {"name": "zstd", "configuration": {"level": 0, "checksum": True}} in meta["codecs"]


CHUNK = os.path.join("data", "action", "c", "0", "0")


@pytest.mark.parametrize("damage, problem", [
    # bytes inside the compressed stream changed: zstd's content checksum catches it at decode
    (lambda p: overwrite(os.path.join(p, CHUNK), 100, b"\xff" * 16),
     f"data/action chunk 0 ({CHUNK}) fails to decode (RuntimeError: Zstd decompression error: "),
    (lambda p: overwrite(os.path.join(p, CHUNK), 0, b"\xff" * 8),
     f"data/action chunk 0 ({CHUNK}) fails to decode (RuntimeError: "),
    (lambda p: cut(os.path.join(p, CHUNK)), f"data/action chunk 0 ({CHUNK}) fails to decode (RuntimeError: "),
    # another array's chunk in its place: it decodes to the wrong size
    (lambda p: shutil.copy(os.path.join(p, "data", "state", "c", "0", "0"), os.path.join(p, CHUNK)),
     f"data/action chunk 0 ({CHUNK}) fails to decode (ValueError: cannot reshape array of size 180"),
    # deleted chunks: zarr would read the fill value (zeros) silently
    (lambda p: os.remove(os.path.join(p, CHUNK)), f"data/action chunk 0 ({CHUNK}) is missing"),
    (lambda p: os.remove(os.path.join(p, "meta", "episode_ends", "c", "0")),
     f"meta/episode_ends chunk 0 ({os.path.join('meta', 'episode_ends', 'c', '0')}) is missing"),
    # metadata
    (lambda p: cut(os.path.join(p, "data", "action", "zarr.json")),
     "data/action/zarr.json is not valid JSON (Expecting "),
    (lambda p: cut(os.path.join(p, "zarr.json")), "zarr.json is not valid JSON ("),
    (lambda p: cut(os.path.join(p, "data", "zarr.json"), 0.0), "data/zarr.json is not valid JSON (it is empty)"),
    (lambda p: os.remove(os.path.join(p, "data", "action", "zarr.json")),
     "data/action has no zarr.json (its metadata is missing)"),
    (lambda p: os.remove(os.path.join(p, "zarr.json")),
     "holds no zarr.json at its root (not a zarr buffer, or its metadata is missing)"),
    # metadata that parses but was edited: the shape (fewer frames read) or the stored SHA-256
    (lambda p: _edit(os.path.join(p, "data", "action", "zarr.json"), "60", "50"),
     "data/action does not match the SHA-256 stored when it was written"),
    (lambda p: _edit(os.path.join(p, "data", "action", "zarr.json"), '"sha256": "', '"sha256": "0'),
     "data/action does not match the SHA-256 stored when it was written"),
], ids=["chunk-bytes", "chunk-header", "chunk-cut", "chunk-swapped", "chunk-deleted", "ends-chunk-deleted",
        "array-meta-cut", "root-meta-cut", "group-meta-emptied", "array-meta-deleted", "root-meta-deleted",
        "shape-edited", "sha-edited"])
def test_a_damaged_buffer_is_one_line_naming_the_part(tmp_path, damage, problem):
    path, _ = _buffer(tmp_path / "demos.zarr")
    damage(path)
    with pytest.raises(BufferDamaged) as e:
        ReplayBuffer.load(path)
    one_line(str(e.value), f"{path}: {problem}", f"; {HINT}")
    assert isinstance(e.value, jsonio.DamagedFileError) and isinstance(e.value, ValueError)
    assert str(e.value.with_hint("delete it to collect it again")).endswith("; delete it to collect it again")


def _edit(path: str, old: str, new: str) -> None:
    text = Path(path).read_text()
    assert old in text
    Path(path).write_text(text.replace(old, new, 1))


def test_a_chunk_damaged_in_a_later_chunk_is_named_by_its_index(tmp_path):
    path = str(tmp_path / "long.zarr")
    frames = np.arange(2 * 600_000, dtype=np.float32).reshape(600_000, 2)  # 4.8 MB: two chunks of ~4 MiB
    ReplayBuffer(data={"action": frames}, episode_ends=np.array([600_000])).save(path)
    assert sorted(os.listdir(os.path.join(path, "data", "action", "c"))) == ["0", "1"]
    second = os.path.join(path, "data", "action", "c", "1", "0")
    overwrite(second, os.path.getsize(second) // 2, b"\x00" * 8)
    with pytest.raises(BufferDamaged, match=r"data/action chunk 1 \(data/action/c/1/0\) fails to decode"):
        ReplayBuffer.load(path)
    os.remove(second)
    with pytest.raises(BufferDamaged, match=r"data/action chunk 1 \(data/action/c/1/0\) is missing;"):
        ReplayBuffer.load(path)


def _unchecked_buffer(path: str) -> str:
    """A buffer as Diffusion Policy's zarr (or this project's before checksums) writes it: default codec, no
    SHA-256, chunks holding only the fill value left out."""
    root = zarr.open_group(path, mode="w")
    rng = np.random.default_rng(1)
    root.create_group("data").create_array("action", data=rng.normal(size=(40, 2)).astype(np.float32),
                                           chunks=(10, 2))
    root.create_group("meta").create_array("episode_ends", data=np.array([20, 40]))
    return path


def test_an_unchecked_buffer_is_checked_as_far_as_zarr_can(tmp_path, capsys):
    """Without stored checksums a chunk that fails to decode and metadata that does not parse are still named; a
    missing data chunk reads as the fill value with a one-line note (it cannot be told from a chunk left out for
    holding only that value); a missing episode_ends chunk (never all zeros) is an error."""
    path = _unchecked_buffer(str(tmp_path / "dp.zarr"))
    assert ReplayBuffer.load(path).num_frames == 40 and capsys.readouterr().err == ""
    chunk = os.path.join(path, "data", "action", "c", "2", "0")
    kept = Path(chunk).read_bytes()
    overwrite(chunk, 0, b"\xff" * 8)
    with pytest.raises(BufferDamaged) as e:
        ReplayBuffer.load(path)
    one_line(str(e.value), f"{path}: data/action chunk 2 (data/action/c/2/0) fails to decode (RuntimeError: ", HINT)
    os.remove(chunk)
    back = ReplayBuffer.load(path)
    assert (back.data["action"][20:30] == 0).all()
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and one_line(err.strip(), f"[data] {path}: 1 chunk(s) of data/action have no file "
                                             f"(first data/action/c/2/0) and read as its fill value 0.0")
    Path(chunk).write_bytes(kept)
    os.remove(os.path.join(path, "meta", "episode_ends", "c", "0"))
    with pytest.raises(BufferDamaged, match="meta/episode_ends chunk 0 .* is missing"):
        ReplayBuffer.load(path)


def test_a_buffer_the_meta_world_bridge_wrote_is_checked_alike(tmp_path):
    """The bridge (its own venv, no project import) stores the same SHA-256 and chunk checksums."""
    from metaworld_bridge.store import write_buffer

    rng = np.random.default_rng(2)
    path = str(tmp_path / "metaworld_assembly_2.zarr")
    data, ends = write_buffer(path, [{"state": rng.normal(size=(15, 39)).astype(np.float32),
                                      "action": rng.normal(size=(15, 4)).astype(np.float32)} for _ in range(2)],
                              attrs={"task": "assembly"})
    meta = json.loads(Path(path, "data", "state", "zarr.json").read_text())
    assert meta["attributes"]["sha256"] == array_sha256(data["state"])
    assert np.array_equal(ReplayBuffer.load(path).data["state"], data["state"])
    overwrite(os.path.join(path, "data", "state", "c", "0", "0"), 200, b"\x00" * 4)
    with pytest.raises(BufferDamaged) as e:
        ReplayBuffer.load(path)
    one_line(str(e.value), f"{path}: data/state chunk 0 (data/state/c/0/0) fails to decode (RuntimeError: ", HINT)


def test_a_damaged_kept_external_evaluation_is_made_again(tmp_path):
    """An external evaluation kept in the run dir is a cache: one that does not read is said in one line and made
    again (the stated fallback), never a traceback."""
    from hipolicy_jax.runs.external import read_kept

    path = write_json(str(tmp_path / "eval" / "step_10.json"), {"successes": 3, "episodes": 4, "settings": {}})
    lines: list[str] = []
    assert read_kept(path, lines.append)["successes"] == 3 and lines == []
    cut(path)
    assert read_kept(path, lines.append) is None
    assert len(lines) == 1
    one_line(lines[0], f"[external] {path}: not valid JSON (", "; this kept evaluation is made again")
    assert read_kept(str(tmp_path / "none.json"), lines.append) is None and len(lines) == 1


def test_training_on_a_damaged_buffer_ends_in_one_line(tmp_path, monkeypatch):
    """``experiments.train --data <damaged>`` (the dry run: it reads the buffer first) exits with ``error: ...``."""
    path, _ = _buffer(tmp_path / "demos.zarr")
    overwrite(os.path.join(path, CHUNK), 100, b"\xff" * 16)
    monkeypatch.setattr(cli, "enable_compilation_cache", lambda *a, **k: None)
    monkeypatch.setattr(sys, "unraisablehook", sys.unraisablehook)
    monkeypatch.setattr(sys, "argv", ["train", "--task", "press_button", "--data", path, "--dry-run",
                                      "--out", str(tmp_path / "run")])
    with pytest.raises(SystemExit) as e:
        runpy.run_module("experiments.train", run_name="__main__")
    one_line(str(e.value.code), f"error: {path}: data/action chunk 0 ({CHUNK}) fails to decode", HINT)


# ------------------------------------------------------------------------------------------------- campaigns
def _recorded(camp: Campaign, job: Job) -> str:
    """Write the record of ``job``'s run holding its evaluation, as the campaign keeps one; → its path."""
    cfg = camp.run_config(job.task, job.col, job.seed, dict(job.changes))
    key = camp._key(job.col, job.seed)[1]
    net = {"params_sha256": None, "final_loss": 0.1}
    record = {"version": RECORD_VERSION, "budget": camp.budget, "network": net,
              "policy": config_to_dict(cfg.policy), "train": config_to_dict(cfg.train),
              "training": {"steps": 10, "wall_time_s": 100.0, "cpu_cores": 1},
              "evaluations": {key: {"settings": json.loads(key), "success_rate": 0.5, "success": [True, False],
                                    "steps": [10, 20], "eval_s": 5.0, "cpu_cores": 2, "network": net}}}
    return write_json(record_path(camp.records, camp.runs, cfg), record)


def test_a_campaign_skips_the_jobs_of_damaged_files_goes_on_and_lists_them(tmp_path, capsys):
    camp = Campaign("smoke", runs=str(tmp_path / "runs"), data=str(tmp_path / "data"),
                    records=str(tmp_path / "records"), episodes=2, progress=False)
    dp = Column("DP", changes=DP)
    jobs = [Job("press_button", dp, seed) for seed in range(4)]
    _recorded(camp, jobs[0])
    damaged_record = _recorded(camp, jobs[1])
    cut(damaged_record)
    _recorded(camp, jobs[2])
    # job 3 is not recorded: it trains first, on demos whose buffer is damaged
    demos = camp.run_config("press_button", dp, 3).data_path()
    _buffer(Path(demos))
    overwrite(os.path.join(demos, CHUNK), 100, b"\xff" * 16)
    # a damaged record of another budget: the cost model leaves it out
    other = _recorded(Campaign("cpu", runs=str(tmp_path / "runs"), records=str(tmp_path / "records")), jobs[0])
    cut(other, 0.3)

    model = CostModel(camp.records, camp.runs)
    assert set(model.damaged) == {damaged_record, other}
    costs = model.estimate(camp, jobs)
    assert [c["done"] for c in costs] == [True, False, True, False]
    assert costs[1]["damaged"].startswith(f"{damaged_record}: not valid JSON (") and "damaged" not in costs[3]
    skipped = work_off(camp, costs, lambda j: camp.run_config(j.task, j.col, j.seed, dict(j.changes)).out_dir(),
                       progress=False)
    out = [line for line in capsys.readouterr().out.splitlines() if line.startswith("[campaign]")]
    record_reason = one_line(costs[1]["damaged"], f"git checkout -- {damaged_record}",
                             "delete it to redo that run's evaluations")
    buffer_reason = (f"{demos}: data/action chunk 0 ({CHUNK}) fails to decode (RuntimeError: Zstd decompression "
                     f"error: b\"Restored data doesn't match checksum\"); {HINT}")
    labels = [f"{i}/4: press_button seed {i - 1} DP {changes_text({})}" for i in (2, 4)]
    assert skipped == [(labels[0], record_reason), (labels[1], buffer_reason)]
    assert out[0].endswith(f" {labels[0]}: skipped, {record_reason}")
    assert out[1].endswith(f" {labels[1]}: skipped, {buffer_reason}")  # the job after it went on
    assert out[2:] == ["[campaign] 2 job(s) skipped for a damaged stored file; the others went on:",
                       f"[campaign]   {labels[0]}: {record_reason}", f"[campaign]   {labels[1]}: {buffer_reason}",
                       "[campaign] 1 record(s) do not read and were left out of the cost estimates:",
                       f"[campaign]   {model.damaged[other]}"]
    assert not os.path.exists(os.path.join(camp.run_config("press_button", dp, 3).out_dir(), "summary.json"))
    assert camp.evaluate(*jobs[2]) is not None  # the other records are untouched


def test_a_table_from_records_fails_on_a_damaged_record_in_one_line(tmp_path, monkeypatch):
    """A table must not drop a run silently: ``--from-records`` on a damaged record ends in ``error: <path>: ...``."""
    from experiments import paper

    argv = ["execution", "--budget", "smoke", "--tasks", "press_button", "--seeds", "0", "--from-records",
            "--runs", str(tmp_path / "runs"), "--records", str(tmp_path / "records"), "--results",
            str(tmp_path / "results"), "--data", str(tmp_path / "data"), "--no-progress"]
    camp = tables.campaign(paper.parse_args(argv))
    paths = {_recorded(camp, Job("press_button", col, 0)) for col in tables.EXECUTION}
    for p in paths:
        cut(p)
    monkeypatch.setattr(cli, "enable_compilation_cache", lambda *a, **k: None)
    with pytest.raises(SystemExit) as e:
        cli.run_table_cli(paper.parse_args, paper.main, argv)
    message = one_line(str(e.value.code), "error: ", ": not valid JSON (", "delete it to redo that run's evaluations")
    assert any(message.startswith(f"error: {p}: ") for p in paths)
    assert not (tmp_path / "results" / "execution.md").exists()


def test_the_campaign_command_skips_a_damaged_record_and_its_plan_lists_it(tmp_path, monkeypatch, capsys):
    """``experiments.paper campaign`` end to end: the job whose record is damaged is skipped with its one line, the
    others go on (here skipped by a past --until: nothing trains), the end lists it and the plan names the file."""
    from experiments import paper

    argv = ["campaign", "--budget", "smoke", "--tasks", "press_button", "--seeds", "0", "--regimes", "r100",
            "--obs-types", "state", "--runs", str(tmp_path / "runs"), "--records", str(tmp_path / "records"),
            "--results", str(tmp_path / "results"), "--data", str(tmp_path / "data"), "--no-progress",
            "--until", "2000-01-01 00:00", "--no-tables"]
    args = paper.parse_args(argv)
    camp = tables.campaign(args)
    jobs, _ = tables.campaign_jobs(args, tables.protocol_tables(args))
    bad = _recorded(camp, jobs[0])
    cut(bad)
    sharing = [j for j in jobs if record_path(camp.records, camp.runs, camp.run_config(
        j.task, j.col, j.seed, dict(j.changes))) == bad]  # the columns evaluated on that run
    monkeypatch.setattr(cli, "enable_compilation_cache", lambda *a, **k: None)
    cli.run_table_cli(paper.parse_args, paper.main, argv)
    out = capsys.readouterr().out.splitlines()
    skipped = [line for line in out if f": skipped, {bad}: not valid JSON (" in line]
    assert len(skipped) == len(sharing) and all(one_line(line, "delete it to redo that run's evaluations")
                                                for line in skipped)
    assert sum(": skipped, estimated " in line for line in out) == len(jobs) - len(sharing)  # the others went on
    assert f"[campaign] {len(sharing)} job(s) skipped for a damaged stored file; the others went on:" in out
    plan = (tmp_path / "results" / "campaign_plan.md").read_text()
    assert f"Skipped, their record does not read ({len(sharing)} evaluations;" in plan
    assert f"- {bad}: not valid JSON (" in plan
