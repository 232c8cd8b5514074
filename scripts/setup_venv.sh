#!/usr/bin/env bash
# Create .venv with Python 3.12 (jax 0.12 needs it) and install the project with its dev extras.
# Picks `python3.12` when it runs, else pyenv's newest 3.12; fails with a one-line message otherwise.
set -euo pipefail
cd "$(dirname "$0")/.."
if python3.12 -c "" >/dev/null 2>&1; then
  PY=(python3.12)
elif command -v pyenv >/dev/null 2>&1 && pyenv versions --bare 2>/dev/null | grep -q '^3\.12'; then
  PY=(env "PYENV_VERSION=$(pyenv versions --bare | grep '^3\.12' | tail -n 1)" python)
else
  echo "error: Python 3.12 not found (jax 0.12 needs >= 3.12): install it, e.g. 'pyenv install 3.12'" >&2
  exit 1
fi
"${PY[@]}" -m venv .venv
. .venv/bin/activate
python --version
pip install -q --upgrade pip
pip install -q -e ".[dev]"
