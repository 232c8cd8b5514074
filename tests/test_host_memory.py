"""``host_memory.keep_freed_memory``: a train step's large buffers are reused without page faults once glibc's heap
has grown to the step's size, and it can be turned off. Counted in fresh processes (the one-arena limit binds only
threads that have not allocated yet)."""

import json
import os
import subprocess
import sys

import pytest

from hipolicy_jax import host_memory

PROBE = r"""
import json, resource, sys
from hipolicy_jax.host_memory import keep_freed_memory
took = keep_freed_memory(None if sys.argv[1] == "env" else sys.argv[1] == "keep")
import jax
from benchmarks.common import ACTION_DIM, STATE_DIM, BenchModel
from benchmarks.studies.point_encoder import Step
keep_freed_memory(None if sys.argv[1] == "env" else sys.argv[1] == "keep")  # importing benchmarks turned it on
# a point-cloud train step whose activations (4 windows x 6 frames x 2048 points x 256 channels) are 50 MB each:
# glibc mmaps them by default
policy = BenchModel("tiny", "pointcloud", {}, STATE_DIM, ACTION_DIM).policy(**{"encoder.num_points": 2048})
step = Step(policy, "written backward", sys.argv[1] != "default", 4)
for _ in range(3):
    jax.block_until_ready(step())
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(3):
    jax.block_until_ready(step())
print(json.dumps({"took": took, "faults_per_call": (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 3}))
"""
PAGES = 50 * 2**20 // 4096  # one activation's pages


def _probe(mode: str, env: dict | None = None) -> dict:
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, timeout=300,
                         env={**os.environ, "JAX_PLATFORMS": "cpu", **(env or {})})
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.slow  # three fresh processes, each compiling a point-cloud train step (~20 s each)
@pytest.mark.skipif(host_memory._glibc() is None, reason="glibc only")
def test_kept_memory_is_reused_without_page_faults():
    kept, default, off = _probe("keep"), _probe("default"), _probe("env", {host_memory.ENV: "0"})
    assert kept["took"] is True and default["took"] is False and off["took"] is False
    assert kept["faults_per_call"] < 0.05 * PAGES, kept  # the heap reached its size: the step reuses its pages
    assert default["faults_per_call"] > 2 * PAGES, default  # glibc's defaults: fresh mmaps every step
    assert off["faults_per_call"] > 2 * PAGES, off  # HIPOLICY_KEEP_FREED_MEMORY=0 leaves glibc's defaults


def test_keep_freed_memory_reports_what_it_did(monkeypatch):
    """Turned off by the environment it leaves glibc alone and says so; without glibc it says False."""
    monkeypatch.setenv(host_memory.ENV, "0")
    assert host_memory.keep_freed_memory() is False
    monkeypatch.setattr(host_memory, "_glibc", lambda: None)
    assert host_memory.keep_freed_memory(True) is False
