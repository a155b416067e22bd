#!/usr/bin/env bash
# Stops the vasld started by deploy/quickstart.sh (pid in vasl-data/vasld.pid), gracefully.
set -euo pipefail
cd "$(dirname "$0")/.."
pidfile=vasl-data/vasld.pid
if [ ! -f "$pidfile" ]; then
  echo "stop: no $pidfile: vasld is not running from this checkout"
  exit 0
fi
pid="$(cat "$pidfile")"
if kill -0 "$pid" 2>/dev/null; then
  kill -TERM "$pid"
  for _ in $(seq 1 300); do
    kill -0 "$pid" 2>/dev/null || break
    sleep 0.1
  done
  if kill -0 "$pid" 2>/dev/null; then
    echo "stop: vasld ($pid) did not stop within 30 s"
    exit 1
  fi
  echo "stop: vasld ($pid) stopped"
else
  echo "stop: vasld ($pid) was not running"
fi
rm -f "$pidfile"
