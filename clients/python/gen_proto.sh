#!/usr/bin/env bash
# Generates the private gRPC stubs vasl/_proto/vasl_pb2{,_grpc}.py from proto/vasl/v1/vasl.proto
# with grpc_tools.protoc, and makes their imports package-relative. Usage: gen_proto.sh [PYTHON]
# (default: python3 on PATH; it needs grpcio-tools). Idempotent; generated files are git-ignored.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
proto_dir="$here/../../proto/vasl/v1"
out="$here/vasl/_proto"
py="${1:-python3}"
mkdir -p "$out"
"$py" -m grpc_tools.protoc -I "$proto_dir" --python_out="$out" --grpc_python_out="$out" \
  "$proto_dir/vasl.proto"
# grpc_tools writes `import vasl_pb2 as vasl__pb2`; the stubs live inside the package.
sed -i -E 's/^import vasl_pb2 as /from . import vasl_pb2 as /' "$out/vasl_pb2_grpc.py"
echo "gen_proto: wrote $out/vasl_pb2.py and vasl_pb2_grpc.py"
