#!/usr/bin/env bash
# Rebuild and (re)install matlearn into the active venv for development. Serialised with a lock
# so parallel developers do not race on the build directory.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-$( [ -x .venv/bin/python ] && echo .venv/bin/python || echo python3 )}
exec flock /tmp/matlearn-build.lock "$PY" -m pip install --no-build-isolation -q -e . "$@"
