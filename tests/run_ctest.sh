#!/usr/bin/env bash
# Configure, build and run the C++ unit tests (plain CMake, no Python bindings) in build/ctest.
set -euo pipefail
cd "$(dirname "$0")/.."
cmake -S . -B build/ctest -DMATLEARN_BUILD_TESTS=ON -DMATLEARN_BUILD_PYTHON=OFF \
  -DCMAKE_BUILD_TYPE=${BUILD_TYPE:-Release} >/dev/null
cmake --build build/ctest -j "${JOBS:-2}"
cd build/ctest && ctest --output-on-failure "$@"
