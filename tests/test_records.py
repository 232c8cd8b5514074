"""Run records hold one network: parameter fingerprints, superseding another network's evaluations, the version-1
upgrade from git history, and the check that the committed records obey the rule."""

import copy
import json
import os
import subprocess

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hipolicy_jax.runs import records as rec_lib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _key(execution, guided=True):
    return json.dumps({"execution": execution, "guided": guided, "percentiles": None}, sort_keys=True)


def test_fingerprint_sees_every_bit_and_ignores_dict_order():
    params = {"a": {"w": jnp.arange(6.0).reshape(2, 3), "b": jnp.zeros(3)}, "c": jnp.ones(2, jnp.bfloat16)}
    h = rec_lib.params_fingerprint(params)
    assert h == rec_lib.params_fingerprint({"c": params["c"], "a": {"b": params["a"]["b"], "w": params["a"]["w"]}})
    bumped = jax.tree.map(lambda x: x, params)
    bumped["a"]["w"] = params["a"]["w"].at[1, 2].set(np.nextafter(np.float32(5.0), np.float32(6.0)))  # one ulp
    assert rec_lib.params_fingerprint(bumped) != h
    assert rec_lib.params_fingerprint({**params, "c": params["c"].astype(jnp.float32)}) != h  # dtype counts
    assert rec_lib.params_fingerprint({"a": {"w": params["a"]["w"].reshape(3, 2), "b": params["a"]["b"]},
                                       "c": params["c"]}) != h  # shape counts


def test_same_network_prefers_the_hash_then_the_exact_loss():
    a = {"params_sha256": "a" * 64, "final_loss": 0.1}
    assert rec_lib.same_network(a, {"params_sha256": "a" * 64, "final_loss": 0.2})
    assert not rec_lib.same_network(a, {"params_sha256": "b" * 64, "final_loss": 0.1})
    assert rec_lib.same_network(a, {"params_sha256": None, "final_loss": 0.1})  # a version-1 evaluation
    assert not rec_lib.same_network(a, {"params_sha256": None, "final_loss": 0.1000000000000001})
    assert not rec_lib.same_network(a, None) and not rec_lib.same_network({"final_loss": None}, {"final_loss": None})


def test_supersede_keeps_one_network():
    old, new = {"params_sha256": "a" * 64, "final_loss": 0.1}, {"params_sha256": "b" * 64, "final_loss": 0.2}
    record = {"version": 2, "network": old, "training": {"final_loss": 0.1}, "calibration": {"thresholds": [1]},
              "evaluations": {_key("chunk"): {"network": old, "success": [True]},
                              _key("te"): {"network": old, "success": [False]}}}
    out = rec_lib.supersede(record, new)
    assert out["network"] == new and out["evaluations"] == {}
    assert out["superseded"] == [{"network": old, "training": {"final_loss": 0.1}, "calibration": {"thresholds": [1]},
                                  "evaluations": record["evaluations"]}]
    assert record["network"] == old  # the input is left alone
    # the same network known by its loss only (version 1) gains the hash; nothing moves
    v1 = {"params_sha256": None, "final_loss": 0.1}
    same = rec_lib.supersede({**record, "network": v1}, old)
    assert same["network"] == old and list(same["evaluations"]) == list(record["evaluations"])
    assert "superseded" not in same


def test_upgrade_v1_supersedes_the_evaluations_of_an_earlier_training():
    record = {"version": 1, "training": {"final_loss": 0.3},
              "evaluations": {_key("chunk"): {"success": [True]}, _key("te"): {"success": [True]},
                              _key("aac"): {"success": [False]}}}
    # chunk was made on an earlier training (loss 0.25); te's first commit is unknown to git: the current training
    out = rec_lib.upgrade_v1(record, {_key("chunk"): 0.25, _key("aac"): 0.3})
    assert out["version"] == 2 and out["network"] == {"params_sha256": None, "final_loss": 0.3}
    assert sorted(out["evaluations"]) == sorted([_key("te"), _key("aac")])
    assert list(out["superseded"][0]["evaluations"]) == [_key("chunk")]
    assert out["superseded"][0]["evaluations"][_key("chunk")]["network"]["final_loss"] == 0.25
    # the superseded entry names the network its evaluations were made on; the record's training summary was the
    # later network's, so it does not travel with them
    assert out["superseded"][0]["network"] == {"params_sha256": None, "final_loss": 0.25}
    assert "training" not in out["superseded"][0]
    assert rec_lib.problems(out) == [] and rec_lib.upgrade_v1(out, {}) == out
    assert rec_lib.problems(record) == ["version 1 (< 2): no network fingerprints"]
    mixed = copy.deepcopy(out)
    mixed["evaluations"][_key("te")]["network"] = {"params_sha256": None, "final_loss": 0.25}
    assert len(rec_lib.problems(mixed)) == 1 and "te/guided=True" in rec_lib.problems(mixed)[0]


def test_git_first_losses_reads_the_training_each_evaluation_first_appeared_with(tmp_path):
    def git(*args):
        subprocess.run(["git", "-C", str(tmp_path), *args], check=True, capture_output=True)

    git("init", "-q")
    git("config", "user.email", "t@example.com")
    git("config", "user.name", "t")
    path = tmp_path / "runs" / "seed0.json"
    path.parent.mkdir()
    snapshots = [{"training": {"final_loss": 0.5}, "evaluations": {_key("chunk"): {}}},
                 {"training": {"final_loss": 0.4}, "evaluations": {_key("chunk"): {}, _key("te"): {}}}]
    for i, snap in enumerate(snapshots):
        path.write_text(json.dumps(snap))
        git("add", ".")
        git("commit", "-qm", f"c{i}")
    assert rec_lib.git_first_losses(str(path)) == {_key("chunk"): 0.5, _key("te"): 0.4}
    outside = tmp_path.parent / "not_a_repo_record.json"
    outside.write_text("{}")
    assert rec_lib.git_first_losses(str(outside)) == {}


def test_committed_records_hold_one_network_each():
    """Every record under results/runs is version 2 and holds evaluations of its own network only."""
    from experiments import records as records_cli

    bad = {}
    for path in records_cli.record_files(os.path.join(ROOT, "results", "runs")):
        with open(path) as f:
            problems = rec_lib.problems(json.load(f))
        if problems:
            bad[path] = problems
    assert not bad, bad


def test_records_cli_check_and_upgrade(tmp_path, capsys):
    from experiments import records as records_cli

    path = tmp_path / "cpu" / "t" / "state" / "dp" / "seed0.json"
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps({"version": 1, "training": {"final_loss": 0.1}, "evaluations": {_key("chunk"): {}}}))
    assert records_cli.main(records_cli.RecordsArgs("check", str(tmp_path))) == 1
    assert "version 1 (< 2)" in capsys.readouterr().out
    assert records_cli.main(records_cli.RecordsArgs("upgrade", str(tmp_path))) == 0
    assert records_cli.main(records_cli.RecordsArgs("check", str(tmp_path))) == 0
    assert "1 of 1 records hold one network" in capsys.readouterr().out
    with pytest.raises(FileNotFoundError, match="not a directory of run records"):
        records_cli.record_files(str(tmp_path / "missing"))
