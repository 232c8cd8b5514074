#!/usr/bin/env bash
# Create .venv with Python 3.12 (jax 0.12 needs it) and install the project with its dev extras.
# Looks for a working Python 3.12 in this order: `python3.12` on PATH, pyenv's installs
# ($PYENV_ROOT, ~/.pyenv, /root/.pyenv, /opt/pyenv), then the usual system prefixes (scripts/lib/python312.sh).
# Fails with a one-line message (and what it tried) when there is none.
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/lib/python312.sh

PY=$(find_python312 "jax 0.12 needs >= 3.12") || exit 1
"$PY" -m venv .venv
. .venv/bin/activate
python --version
pip install -q --upgrade pip
pip install -q -e ".[dev]"
# openpi's client, for the tests that drive the policy server with it: it pins numpy<2, which jax 0.12 cannot use,
# and its code runs on numpy 2, so it goes in without its dependencies (its other ones are in .[dev])
pip install -q --no-deps "openpi-client==0.1.2"
