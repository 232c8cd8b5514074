"""The Meta-World venv the bridge tests run in (``bash scripts/setup_metaworld.sh`` → ``.venv-metaworld``;
``METAWORLD_VENV`` chooses another), the skip marker for its absence, and ways to run code in it."""

from __future__ import annotations

import os
import subprocess

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
VENV = os.path.join(ROOT, os.environ.get("METAWORLD_VENV", ".venv-metaworld"))
PYTHON = os.path.join(VENV, "bin", "python")

needs_venv = pytest.mark.skipif(not os.path.exists(PYTHON),
                                reason=f"no Meta-World venv at {VENV}: run `bash scripts/setup_metaworld.sh`")


def bridge(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """``python -m metaworld_bridge.<args>`` in the Meta-World venv, from the repository root."""
    return subprocess.run([PYTHON, "-m", *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout)


def in_bridge(code: str, timeout: float = 300) -> str:
    """Run ``code`` with the Meta-World venv's python from the repository root; → its stdout (it must print ok)."""
    r = subprocess.run([PYTHON, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0 and r.stdout.strip().endswith("ok"), (r.stdout[-2000:], r.stderr[-3000:])
    return r.stdout
