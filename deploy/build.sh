#!/usr/bin/env bash
# Configures and builds vasl (Release, Ninja) into build/: libvasl, vasld, the unit tests and
# the vasl_scene tool. Extra arguments go to the CMake configure step (e.g. -DVASL_NATIVE=ON).
set -euo pipefail
cd "$(dirname "$0")/.."
cmake -S . -B build -G Ninja -DCMAKE_BUILD_TYPE=Release "$@" > build-configure.log 2>&1 || {
  cat build-configure.log; exit 1; }
rm -f build-configure.log
cmake --build build -j "$(nproc)"
echo "build: done (binaries: build/server/vasld, build/tests/scenes/vasl_scene)"
