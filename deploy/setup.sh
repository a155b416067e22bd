#!/usr/bin/env bash
# Installs everything vasl needs on a Debian 12 machine: build tools, the C++ libraries from
# Debian's packages, and the Python client's virtual environment (.venv) from PyPI.
# Idempotent: a second run installs nothing new. Must run as root (or with sudo available).
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

# Python client in a virtual environment; the interpreter is whichever python3 is on PATH.
if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
if ! .venv/bin/python -c "import grpc, grpc_tools, numpy, pytest, pye57, vasl" 2>/dev/null; then
  .venv/bin/pip install -q --upgrade pip
  .venv/bin/pip install -q -r clients/python/requirements.txt
  .venv/bin/pip install -q -e clients/python
fi
echo "setup: done"
