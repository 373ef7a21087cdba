#!/usr/bin/env bash
# The lent GPU machine's one command (scripts/device.py's docstring; docs/training.md, "A lent
# GPU"): install only the carried wheels the device lacks, then every stage of the call within
# MINUTES of wall time, writing to $OUT.
#   bash scripts/device_run.sh MINUTES [--dry-run]
# PYTHON (default python3) and DEVICE_CARRY (default .device, what device.py prepare wrote).
set -euo pipefail
cd "$(dirname "$0")/.."
minutes=${1:?usage: bash scripts/device_run.sh MINUTES [--dry-run]}
shift
PY=${PYTHON:-python3}
carry=${DEVICE_CARRY:-.device}
wheels=$($PY scripts/device.py missing --wheels "$carry/wheels")
if [ -n "$wheels" ]; then
  # shellcheck disable=SC2086  # one argument per wheel
  $PY -m pip install --quiet --no-index --no-deps --no-compile --target /tmp/device_site $wheels
  export PYTHONPATH=/tmp/device_site${PYTHONPATH:+:$PYTHONPATH}
fi
export XLA_PYTHON_CLIENT_PREALLOCATE=false
exec "$PY" scripts/device.py run --minutes "$minutes" --carry "$carry" "$@"
