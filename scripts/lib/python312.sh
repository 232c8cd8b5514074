# Sourced by the setup scripts (scripts/setup_venv.sh, scripts/setup_metaworld.sh): find a working Python 3.12.
#
#   . scripts/lib/python312.sh
#   PY=$(find_python312) || exit 1      # prints the interpreter's path, or a one-line error on stderr
#
# Looks in this order: `python3.12` on PATH, pyenv's installs ($PYENV_ROOT, ~/.pyenv, /root/.pyenv, /opt/pyenv,
# /usr/local/pyenv; newest 3.12.x first), then the usual system prefixes. The error names what it tried.

is_python312() { "$1" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 12))' >/dev/null 2>&1; }

# find_python312 [why]: echo the first Python 3.12 that runs; else print "error: ..." (with `why`, e.g. "jax 0.12
# needs >= 3.12") and what was tried to stderr and return 1.
find_python312() {
  local why="${1:-}" root dir c
  local candidates=(python3.12) tried=()
  for root in "${PYENV_ROOT:-}" "${HOME:-}/.pyenv" /root/.pyenv /opt/pyenv /usr/local/pyenv; do
    [ -n "$root" ] || continue
    for dir in $(ls -d "$root"/versions/3.12* 2>/dev/null | sort -V -r); do
      candidates+=("$dir/bin/python3.12" "$dir/bin/python")
    done
  done
  candidates+=(/usr/local/bin/python3.12 /usr/bin/python3.12 /opt/python3.12/bin/python3.12)
  for c in "${candidates[@]}"; do
    tried+=("$c")
    if is_python312 "$c"; then
      command -v "$c" 2>/dev/null || echo "$c"
      return 0
    fi
  done
  echo "error: Python 3.12 not found (${why:+$why; }tried: ${tried[*]}): install it, e.g. 'pyenv install 3.12'" >&2
  return 1
}
