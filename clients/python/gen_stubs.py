"""Generates the private gRPC stubs vasl/_proto/vasl_pb2{,_grpc}.py from the repository's
proto/vasl/v1/vasl.proto with grpc_tools.protoc and makes their imports package-relative.
Run by gen_proto.sh (deploy/setup.sh) and by the package build (setup.py), so that
`pip install ./clients/python` gives a working client. Usage: python gen_stubs.py"""
from __future__ import annotations

import os
import re
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
PROTO_DIR = os.path.normpath(os.path.join(HERE, "..", "..", "proto", "vasl", "v1"))
OUT = os.path.join(HERE, "vasl", "_proto")


def generate() -> bool:
    """Writes the stubs; False (nothing written) when the proto is not there (a source
    distribution, which ships the stubs instead)."""
    proto = os.path.join(PROTO_DIR, "vasl.proto")
    if not os.path.exists(proto):
        return False
    os.makedirs(OUT, exist_ok=True)
    subprocess.run([sys.executable, "-m", "grpc_tools.protoc", "-I", PROTO_DIR,
                    f"--python_out={OUT}", f"--grpc_python_out={OUT}", proto], check=True)
    # grpc_tools writes `import vasl_pb2 as vasl__pb2`; the stubs live inside the package.
    grpc_py = os.path.join(OUT, "vasl_pb2_grpc.py")
    with open(grpc_py) as f:
        text = f.read()
    with open(grpc_py, "w") as f:
        f.write(re.sub(r"^import vasl_pb2 as ", "from . import vasl_pb2 as ", text, flags=re.M))
    return True


if __name__ == "__main__":
    if not generate():
        sys.exit(f"gen_stubs: {PROTO_DIR}/vasl.proto not found")
    print(f"gen_stubs: wrote {OUT}/vasl_pb2.py and vasl_pb2_grpc.py")
