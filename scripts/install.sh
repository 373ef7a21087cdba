#!/usr/bin/env bash
# One install path for a fresh Debian/Ubuntu machine with Python 3.11+:
#   1. libLLVM 19 for Mitsuba's CPU (llvm) backend, via apt when we are root;
#   2. a virtual environment in .venv with the project and its dev extras.
# Idempotent: re-running it only installs what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
LLVM_PKG=libllvm19

have_llvm() {
  ls /usr/lib/*-linux-gnu/libLLVM-19.so* /usr/lib/llvm-19/lib/libLLVM*.so* >/dev/null 2>&1
}

if ! have_llvm; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
    echo "[install] installing $LLVM_PKG (Mitsuba's CPU backend needs LLVM 19; 14 is refused, 15 crashes)"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq "$LLVM_PKG" >/dev/null
  else
    echo "[install] Mitsuba's CPU backend needs LLVM 19. Run once:  sudo apt-get install -y $LLVM_PKG"
    echo "[install] (continuing: everything but the Mitsuba backend works without it)"
  fi
fi

if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
.venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[dev]"
echo "[install] ok: $(.venv/bin/python -c 'import jax, flax, mitsuba; print("jax", jax.__version__, "flax", flax.__version__, "mitsuba", mitsuba.__version__)')"
