"""Smoke test of ``benchmarks.profile_eval`` (the evaluation profile and the compacted-vs-vmapped comparison) on a
tiny untrained policy, and its compile times (cold / warm cache); nothing here asserts a figure."""

import math

import pytest

from hipolicy_jax import jsonio
from benchmarks import profile_eval


@pytest.mark.slow
def test_profile_and_compare_write_finite_json(tmp_path):
    profile_eval.main(["--quick", "--cells", "dp:aac", "--out-dir", str(tmp_path)])
    (row,) = jsonio.load(str(tmp_path / "profile_eval_cpu.json"))["rows"]
    assert row["policy_source"].startswith("untrained") and row["rounds"] == max(row["decisions"])
    for k in ("sampler", "physics + task", "loop bookkeeping"):
        assert math.isfinite(row["split_pct"][k])
    assert 0 < row["useful_fraction"] <= 1 and row["control_steps"] == sum(row["steps"])
    profile_eval.main(["--quick", "--compare", "--cells", "dp:aac", "--block", "2", "--out-dir", str(tmp_path)])
    res = jsonio.load(str(tmp_path / "profile_eval_compare_cpu.json"))
    (row,) = res["rows"]
    assert row["block"] == 2 and row["identical_outcomes"] and row["old"] == row["new"]
    assert row["speedup"] > 0 and math.isfinite(row["new_compile_s"]) and "machine" in res
    assert "identical in 1 of 1 cells; success, steps and decisions in 1." in res["note"]
    profile_eval.main(["--quick", "--compare", "--all-samples", "--cells", "dp:chunk", "--out-dir", str(tmp_path)])
    res = jsonio.load(str(tmp_path / "profile_eval_compare_cpu.json"))
    (row,) = res["rows"]
    assert (row["old_samples_drawn"], row["new_samples_drawn"]) == (4, 1) and row["num_samples"] == 4
    assert row["old"]["success"] == row["new"]["success"] and res["note"].startswith("Old: every decision draws")
    profile_eval.main(["--quick", "--compile", "--full-forward-reset", "--cells", "dp:chunk", "--out-dir",
                       str(tmp_path)])
    res = jsonio.load(str(tmp_path / "profile_eval_compile_cpu.json"))
    (row,) = res["rows"]
    for k in ("cold_s", "warm_cache_s", "reset_alone_s", "env_step_alone_s", "sampler_alone_s", "before_cold_s",
              "before_warm_cache_s", "before_reset_alone_s"):
        assert math.isfinite(row[k]) and row[k] > 0, k
    assert "before: cold s" in res["table_md"]
