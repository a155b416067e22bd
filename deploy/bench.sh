#!/usr/bin/env bash
# Sets up, builds, then prints the speed figures of ingest, reweight, render and record IO on
# the synthetic room (tests/bench/vasl_bench.cc). Arguments go to vasl_bench
# (--panorama-width W, --repeat N, --growth-only, --tile-vossels T, --snapshot-budget-mb M,
# --revisit-cache-mb M, --growth-passes N).
set -euo pipefail
cd "$(dirname "$0")/.."
./deploy/setup.sh
./deploy/build.sh
./build/tests/bench/vasl_bench "$@"
