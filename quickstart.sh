#!/usr/bin/env bash
# matlearn quick start. Usage (as root on a fresh Debian 12 machine, or with sudo available):
#   ./quickstart.sh demo   # install everything, then run the flagship demo
#   ./quickstart.sh test   # install everything, then run all tests (ctest + pytest)
# Installs: Debian packages (Eigen, SuiteSparse/CHOLMOD, TetGen, OpenBLAS, libusb), a virtual
# environment in .venv with matlearn (pip install .) and its test/learning extras.
set -euo pipefail
cd "$(dirname "$0")"
what=${1:-demo}
VENV=${MATLEARN_VENV:-.venv}

SUDO=""
[ "$(id -u)" -ne 0 ] && SUDO=sudo
pkgs="libeigen3-dev libsuitesparse-dev libtet1.5-dev libopenblas0-pthread libusb-1.0-0 cmake g++ python3-venv python3-dev"
missing=""
for p in $pkgs; do dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"; done
if [ -n "$missing" ]; then
  echo "== installing Debian packages:$missing"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq $missing >/dev/null
fi

PY=${PYTHON:-python3}
if [ ! -x "$VENV/bin/python" ]; then
  echo "== creating virtual environment $VENV"
  "$PY" -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install -q --upgrade pip >/dev/null
echo "== installing matlearn (C++ build, ~1-2 min) and dependencies"
# torch is pinned to the CPU build (an unpinned torch pulls a multi-GB CUDA build).
"$VENV/bin/python" -m pip install -q "torch==2.13.0"
"$VENV/bin/python" -m pip install -q ".[learn,test,scan]"

case "$what" in
  demo)
    exec "$VENV/bin/python" examples/demo.py --out demo_out
    ;;
  test)
    echo "== C++ unit tests (ctest)"
    PATH="$PWD/$VENV/bin:$PATH" tests/run_ctest.sh
    echo "== Python tests (pytest)"
    cd tests && exec "../$VENV/bin/python" -m pytest -q -p no:cacheprovider python
    ;;
  *)
    echo "usage: $0 demo|test" >&2
    exit 2
    ;;
esac
