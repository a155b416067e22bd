#!/usr/bin/env bash
# The quick start: set up, build, start vasld in the background on ./vasl-data, write a
# synthetic scan set with vasl_scene, create project `demo` (0.05 m vossels) if missing, ingest
# every scan (skipping those already in), render a panorama from a novel viewpoint into
# ./out/demo.exr + ./out/demo.png. Safe to run again. Stop the server with ./deploy/stop.sh.
# Environment: VASL_ADDRESS (default 127.0.0.1:50051).
set -euo pipefail
cd "$(dirname "$0")/.."
root="$PWD"
address="${VASL_ADDRESS:-127.0.0.1:50051}"

./deploy/setup.sh
./deploy/build.sh

mkdir -p vasl-data out
pidfile=vasl-data/vasld.pid
log=vasl-data/vasld.log
if [ -f "$pidfile" ] && kill -0 "$(cat "$pidfile")" 2>/dev/null; then
  echo "quickstart: vasld already running (pid $(cat "$pidfile"))"
else
  echo "quickstart: starting vasld on $address (log $log)"
  nohup build/server/vasld --address "$address" --data-dir vasl-data >> "$log" 2>&1 &
  echo $! > "$pidfile"
fi
# Wait for the health service to report SERVING.
.venv/bin/python - "$address" "$log" <<'PY'
import sys, time, grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc
address, log = sys.argv[1], sys.argv[2]
deadline = time.monotonic() + 60
with grpc.insecure_channel(address) as ch:
    stub = health_pb2_grpc.HealthStub(ch)
    while time.monotonic() < deadline:
        try:
            if stub.Check(health_pb2.HealthCheckRequest(), timeout=2).status == 1:
                sys.exit(0)
        except grpc.RpcError:
            time.sleep(0.3)
print(f"quickstart: vasld is not serving on {address}; see {log}:", file=sys.stderr)
print(open(log).read()[-2000:], file=sys.stderr)
sys.exit(1)
PY

vasl() { .venv/bin/vasl --server "$address" "$@"; }

if [ -f out/scene/scene.json ]; then
  echo "quickstart: scene already in out/scene"
else
  build/tests/scenes/vasl_scene --out out/scene
fi

if vasl project get demo > /dev/null 2>&1; then
  echo "quickstart: project demo exists"
else
  vasl project create demo --vossel-size 0.05 --description "vasl quickstart"
fi
vasl ingest out/scene/scan-*.json --project demo --skip-existing
vasl project get demo

pose="$(.venv/bin/python -c '
import json
v = {x["name"]: x for x in json.load(open("out/scene/truth/views.json"))["views"]}["novel-1"]
print(",".join(str(c) for c in v["position"] + v["quaternion"]))')"
vasl render --project demo --pose "$pose" --width 2048 --height 1024 -o out/demo.exr
vasl inspect --project demo
vasl versions --project demo
vasl export --project demo -o out/demo.vdb

cat <<MSG

quickstart: done.
  server      vasld on $address, pid $(cat "$pidfile"), log $root/$log
  data        $root/vasl-data/demo/ (catalog.sqlite, blobs/, objects/<sha256> tile files, HEAD)
  scans       $root/out/scene/scan-*.json (+ .ply, -rgb.png), ground truth in out/scene/truth/
  render      $root/out/demo.exr (R,G,B,A,N.x,N.y,N.z,U as half floats, Z as float) and $root/out/demo.png
  CLI         .venv/bin/vasl --server $address scans --project demo
  export      $root/out/demo.vdb: the HEAD version as one OpenVDB file (vdb_print -l out/demo.vdb)
  stop        ./deploy/stop.sh   (or: kill \$(cat vasl-data/vasld.pid))
MSG
