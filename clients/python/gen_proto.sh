#!/usr/bin/env bash
# Generates the private gRPC stubs vasl/_proto/vasl_pb2{,_grpc}.py from proto/vasl/v1/vasl.proto
# (gen_stubs.py, which the package build runs too). Usage: gen_proto.sh [PYTHON] (default:
# python3 on PATH; it needs grpcio-tools). Idempotent; generated files are git-ignored.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
"${1:-python3}" "$here/gen_stubs.py"
