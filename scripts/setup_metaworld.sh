#!/usr/bin/env bash
# Create the Meta-World venv (default .venv-metaworld; METAWORLD_VENV=<dir> chooses another) for metaworld_bridge:
# Python 3.12 with metaworld 3.1.1 (it pins mujoco 3.3.0, which cannot share the project's venv and its mujoco
# 3.17), packaging, numpy, zarr 3, msgpack, websockets, tqdm and openpi's client (openpi-client 0.1.2, installed
# --no-deps: it pins numpy<2, metaworld's numpy is 2.x; it needs only msgpack, numpy, websockets and
# typing_extensions at run time). Never jax: the bridge writes demos to zarr and runs episodes against the policy
# server (metaworld_bridge.evaluate); the project's .venv trains on the demos and serves the policy.
#
# Idempotent: a venv that already imports everything at the pinned versions is left as it is. Fails with one
# line (the pip log's path when an install fails). The bridge is not installed into the venv: run it from the
# repository root, e.g. `.venv-metaworld/bin/python -m metaworld_bridge.collect --task assembly --episodes 10`.
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/lib/python312.sh

VENV="${METAWORLD_VENV:-.venv-metaworld}"
REQS=("metaworld==3.1.1" "packaging" "numpy>=2,<3" "zarr>=3,<4" "msgpack>=1.1" "websockets>=15" "tqdm>=4.66"
      "typing_extensions>=4")
OPENPI_CLIENT="openpi-client==0.1.2"
CHECK='
import importlib.metadata as md, sys
import metaworld, metaworld.policies, gymnasium, mujoco, numpy, zarr, msgpack, websockets, tqdm, packaging
import openpi_client.websocket_client_policy
assert md.version("metaworld") == "3.1.1", md.version("metaworld")
assert md.version("openpi-client") == "0.1.2", md.version("openpi-client")
assert zarr.__version__.split(".")[0] == "3", zarr.__version__
try:
    md.version("jax")
    sys.exit("jax is installed in the Meta-World venv")
except md.PackageNotFoundError:
    pass
'

if [ -x "$VENV/bin/python" ] && "$VENV/bin/python" -c "$CHECK" >/dev/null 2>&1; then
  echo "Meta-World venv ready: $VENV ($("$VENV/bin/python" -c 'import mujoco, metaworld.policies; print("metaworld 3.1.1, mujoco", mujoco.__version__)'))"
  exit 0
fi

if [ -e "$VENV" ] && ! is_python312 "$VENV/bin/python"; then
  echo "error: $VENV exists but is not a Python 3.12 venv; remove it (rm -rf $VENV) or set METAWORLD_VENV" >&2
  exit 1
fi
if [ ! -x "$VENV/bin/python" ]; then
  PY=$(find_python312 "the Meta-World venv uses 3.12") || exit 1
  "$PY" -m venv "$VENV" || { echo "error: could not create a venv at $VENV with $PY" >&2; exit 1; }
fi
LOG="$VENV/setup.log"
if ! { "$VENV/bin/python" -m pip install -q --upgrade pip && "$VENV/bin/python" -m pip install -q "${REQS[@]}" \
      && "$VENV/bin/python" -m pip install -q --no-deps "$OPENPI_CLIENT"; } >"$LOG" 2>&1; then
  echo "error: pip could not install ${REQS[*]} $OPENPI_CLIENT into $VENV (see $LOG: $(grep -m1 -i error "$LOG" || tail -n1 "$LOG"))" >&2
  exit 1
fi
if ! CHECK_OUT=$("$VENV/bin/python" -c "$CHECK" 2>&1); then
  echo "error: the Meta-World venv $VENV does not import its packages: $(echo "$CHECK_OUT" | tail -n1)" >&2
  exit 1
fi
echo "Meta-World venv ready: $VENV ($("$VENV/bin/python" -c 'import mujoco; print("metaworld 3.1.1, mujoco", mujoco.__version__)'))"
