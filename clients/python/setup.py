"""The package build generates the gRPC stubs from the repository's proto (gen_stubs.py) before
it collects the package, so `pip install ./clients/python` needs nothing generated beforehand.
Metadata lives in pyproject.toml."""
import os
import sys

from setuptools import setup
from setuptools.command.build_py import build_py

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import gen_stubs  # noqa: E402


class BuildPyWithStubs(build_py):
    def run(self):
        if not gen_stubs.generate() and not os.path.exists(os.path.join(gen_stubs.OUT, "vasl_pb2.py")):
            raise RuntimeError(f"{gen_stubs.PROTO_DIR}/vasl.proto not found and no stubs shipped")
        super().run()


setup(cmdclass={"build_py": BuildPyWithStubs})
