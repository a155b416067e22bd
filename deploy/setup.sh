#!/usr/bin/env bash
# Installs everything vasl needs on a Debian 12 machine: build tools, the C++ libraries from
# Debian's packages, and the Python client's virtual environment (.venv) from PyPI.
# Then generates the client's gRPC stubs and installs the client (editable) with its `vasl` CLI.
# Idempotent: a second run installs nothing new. Must run as root (or with sudo available);
# works on a fresh Debian 12 minbase (no python3, git, sudo or compilers needed beforehand).
set -euo pipefail
cd "$(dirname "$0")/.."

PKGS=(
  build-essential cmake ninja-build pkg-config git ca-certificates
  python3 python3-venv python3-pip python3-dev
  libopenvdb-dev libopenvdb-tools libboost-iostreams-dev libblosc-dev
  libeigen3-dev
  libopenimageio-dev openimageio-tools
  libopenexr-dev
  libgrpc++-dev protobuf-compiler-grpc libprotobuf-dev protobuf-compiler
  libsqlite3-dev libtbb-dev libgtest-dev libgmock-dev
  libabsl-dev libssl-dev
)

missing=()
for p in "${PKGS[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ "${#missing[@]}" -gt 0 ]; then
  echo "setup: installing ${#missing[@]} Debian packages: ${missing[*]}"
  SUDO=""
  [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
else
  echo "setup: Debian packages already installed"
fi

# Python client in a virtual environment (Debian's python3; pyenv or other shims are ignored
# when /usr/bin/python3 exists, since python3-venv belongs to it).
PY=/usr/bin/python3
[ -x "$PY" ] || PY="$(command -v python3)"
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv with $PY"
  "$PY" -m venv .venv
fi
modules="grpc, grpc_tools, grpc_health.v1, grpc_reflection, numpy, pytest, pye57, OpenEXR"
modules="$modules, tqdm, laspy, lazrs, e57, yaml"
if ! .venv/bin/python -c "import $modules" 2>/dev/null; then
  echo "setup: installing Python packages into .venv (clients/python/requirements.txt)"
  .venv/bin/pip install -q --upgrade pip
  .venv/bin/pip install -q -r clients/python/requirements.txt
fi
# gRPC stubs (private, git-ignored): regenerate when missing or older than the .proto.
stub=clients/python/vasl/_proto/vasl_pb2_grpc.py
if [ ! -f "$stub" ] || [ proto/vasl/v1/vasl.proto -nt "$stub" ]; then
  clients/python/gen_proto.sh .venv/bin/python
fi
if ! .venv/bin/python -c "import vasl, vasl.cli" 2>/dev/null || [ ! -x .venv/bin/vasl ]; then
  echo "setup: installing the vasl client (editable) into .venv"
  .venv/bin/pip install -q -e clients/python
fi
echo "setup: done"
