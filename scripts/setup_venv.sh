#!/usr/bin/env bash
# Create .venv with Python 3.12 (jax 0.12 needs it) and install the project with its dev extras.
# Looks for a working Python 3.12 in this order: `python3.12` on PATH, pyenv's installs
# ($PYENV_ROOT, ~/.pyenv, /root/.pyenv, /opt/pyenv), then the usual system prefixes.
# Fails with a one-line message (and what it tried) when there is none.
set -euo pipefail
cd "$(dirname "$0")/.."

is_312() { "$1" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 12))' >/dev/null 2>&1; }

PY=""
tried=()
candidates=(python3.12)
for root in "${PYENV_ROOT:-}" "${HOME:-}/.pyenv" /root/.pyenv /opt/pyenv /usr/local/pyenv; do
  [ -n "$root" ] || continue
  # Newest 3.12.x first.
  for dir in $(ls -d "$root"/versions/3.12* 2>/dev/null | sort -V -r); do
    candidates+=("$dir/bin/python3.12" "$dir/bin/python")
  done
done
candidates+=(/usr/local/bin/python3.12 /usr/bin/python3.12 /opt/python3.12/bin/python3.12)
for c in "${candidates[@]}"; do
  tried+=("$c")
  if is_312 "$c"; then PY="$c"; break; fi
done
if [ -z "$PY" ]; then
  echo "error: Python 3.12 not found (jax 0.12 needs >= 3.12; tried: ${tried[*]}): install it, e.g. 'pyenv install 3.12'" >&2
  exit 1
fi
"$PY" -m venv .venv
. .venv/bin/activate
python --version
pip install -q --upgrade pip
pip install -q -e ".[dev]"
