#!/usr/bin/env bash
# Sets up, builds, then runs every test: the GoogleTest unit tests (ctest) and the end-to-end
# tests (pytest tests/integration, a real vasld on loopback). Exits non-zero if anything fails,
# including a pytest run that collected no test (exit 5).
set -euo pipefail
cd "$(dirname "$0")/.."
./deploy/setup.sh
./deploy/build.sh

status=0
echo "== unit tests (ctest)"
ctest --test-dir build --output-on-failure || status=1

echo "== end-to-end tests (pytest tests/integration)"
set +e
VASL_BUILD_DIR="$PWD/build" .venv/bin/python -m pytest tests/integration -v -s -p no:cacheprovider
rc=$?
set -e
if [ "$rc" -eq 5 ]; then
  echo "test: pytest collected no test: that is a failure"
  status=1
elif [ "$rc" -ne 0 ]; then
  status=1
fi
if [ "$status" -ne 0 ]; then
  echo "test: FAILED"
else
  echo "test: all passed"
fi
exit "$status"
