#!/usr/bin/env bash
# The long checks (not part of deploy/test.sh): set up and build, then
#   1. crash soak: vasld killed with SIGKILL at random moments during ingests, reweights,
#      back-projections and exports; after each restart the store must be whole
#      (tests/soak/test_crash_soak.py);
#   2. load: concurrent small renders during ingests on loopback: latency, errors, peak RSS
#      (tests/soak/test_load.py);
#   2b. client memory: a synthetic E57 of VASL_SOAK_CLIENT_POINTS points (default 20 M) written
#      chunk by chunk and ingested by the CLI beside a 1 M-point one: the client's peak RSS
#      and each file's size (tests/soak/test_large_e57_client.py);
#   3. the fuzzers, if deploy/fuzz.sh exists, VASL_FUZZ_SECONDS (default 60) per target.
# Prints every `soak:` (and fuzz.sh's `fuzz:`) line again at the end; exits non-zero if anything
# failed.
# Environment:
#   VASL_SOAK_NO_BUILD=1          skip deploy/setup.sh and deploy/build.sh (binaries already built)
#   VASL_BUILD_DIR                binaries (default ./build)
#   VASL_SOAK_INGEST_KILLS=20  VASL_SOAK_REWEIGHT_KILLS=8  VASL_SOAK_BACKPROJECT_KILLS=8
#   VASL_SOAK_EXPORT_KILLS=6  VASL_SOAK_SEED=2026 (kill moments)
#   VASL_SOAK_LOAD_THREADS=8  VASL_SOAK_LOAD_RENDERS=40 (per thread)  VASL_SOAK_LOAD_DEADLINE_S=600
#   VASL_SOAK_LOAD_MAX_INGESTS=6  VASL_SOAK_CLIENT_POINTS=20000000
#   VASL_FUZZ_SECONDS=60          seconds per fuzz target; VASL_SOAK_NO_FUZZ=1 skips fuzzing
# Extra arguments go to pytest (e.g. -k reweight).
set -euo pipefail
cd "$(dirname "$0")/.."

if [ "${VASL_SOAK_NO_BUILD:-0}" != "1" ]; then
  ./deploy/setup.sh
  ./deploy/build.sh
fi
export VASL_BUILD_DIR="${VASL_BUILD_DIR:-$PWD/build}"

status=0
log="$(mktemp -t vasl-soak.XXXXXX)"
trap 'rm -f "$log"' EXIT

echo "== crash soak and load (pytest tests/soak)"
set +e
.venv/bin/python -m pytest tests/soak -v -s -p no:cacheprovider "$@" 2>&1 | tee "$log"
rc=${PIPESTATUS[0]}
set -e
if [ "$rc" -eq 5 ]; then
  echo "soak: pytest collected no test: that is a failure"
  status=1
elif [ "$rc" -ne 0 ]; then
  status=1
fi

if [ "${VASL_SOAK_NO_FUZZ:-0}" = "1" ]; then
  echo "== fuzzing skipped (VASL_SOAK_NO_FUZZ=1)"
elif [ -f deploy/fuzz.sh ]; then
  echo "== fuzzing (deploy/fuzz.sh ${VASL_FUZZ_SECONDS:-60})"
  set +e
  bash deploy/fuzz.sh "${VASL_FUZZ_SECONDS:-60}" 2>&1 | tee -a "$log"
  [ "${PIPESTATUS[0]}" -eq 0 ] || status=1
  set -e
else
  echo "== fuzzing skipped: no deploy/fuzz.sh"
fi

echo "== soak summary"
grep -E '^(soak|fuzz): ' "$log" || echo "(no soak figures printed)"
if [ "$status" -ne 0 ]; then
  echo "soak: FAILED"
else
  echo "soak: all passed"
fi
exit "$status"
