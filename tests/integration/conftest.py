"""Fixtures of the end-to-end tests: a synthetic scan set written by `vasl_scene`, a REAL vasld
on a free loopback port with a temporary data directory, and a project with every scan ingested.

Binaries are taken from $VASL_BUILD_DIR (default <repo>/build): server/vasld and
tests/scenes/vasl_scene. deploy/test.sh builds them first.
"""
from __future__ import annotations

import glob
import json
import os
import signal
import subprocess
import sys
import time

import grpc
import pytest

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
BUILD = os.environ.get("VASL_BUILD_DIR", os.path.join(REPO, "build"))
VASLD = os.path.join(BUILD, "server", "vasld")
VASL_SCENE = os.path.join(BUILD, "tests", "scenes", "vasl_scene")
VOSSEL_M = 0.05
E2E_PROJECT = "e2e"


def _require(path: str) -> str:
    if not os.access(path, os.X_OK):
        pytest.fail(f"{path} is missing: build first (./deploy/build.sh, or set VASL_BUILD_DIR)",
                    pytrace=False)
    return path


class Server:
    """A running vasld."""

    def __init__(self, proc: subprocess.Popen, address: str, data_dir: str, log_path: str):
        self.proc = proc
        self.address = address
        self.data_dir = data_dir
        self.log_path = log_path

    def log(self) -> str:
        with open(self.log_path, "r", errors="replace") as f:
            return f.read()


def _port_file_address(port_file: str, proc: subprocess.Popen, log_path: str,
                       timeout_s: float = 60.0) -> str:
    """Waits for vasld to write its port file and returns its loopback address; fails the test
    with vasld's log when it exits or the wait times out first."""
    deadline = time.monotonic() + timeout_s
    while not os.path.exists(port_file) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    if not os.path.exists(port_file):
        with open(log_path, errors="replace") as f:
            pytest.fail(f"vasld wrote no port file (exit {proc.poll()}):\n{f.read()}",
                        pytrace=False)
    with open(port_file) as f:
        return f"127.0.0.1:{int(f.read().strip())}"


def _wait_serving(address: str, proc: subprocess.Popen, log_path: str, timeout_s: float = 60.0):
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    deadline = time.monotonic() + timeout_s
    with grpc.insecure_channel(address) as channel:
        stub = health_pb2_grpc.HealthStub(channel)
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                break
            try:
                r = stub.Check(health_pb2.HealthCheckRequest(service=""), timeout=2)
                if r.status == health_pb2.HealthCheckResponse.SERVING:
                    return
            except grpc.RpcError:
                pass
            time.sleep(0.2)
    with open(log_path, errors="replace") as f:
        log = f.read()
    pytest.fail(f"vasld at {address} did not become SERVING (exit {proc.poll()}):\n{log}",
                pytrace=False)


@pytest.fixture(scope="session")
def scene_dir(tmp_path_factory) -> str:
    out = str(tmp_path_factory.mktemp("scene"))
    t0 = time.monotonic()
    r = subprocess.run([_require(VASL_SCENE), "--out", out], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.fail(f"vasl_scene failed ({r.returncode}):\n{r.stdout}\n{r.stderr}", pytrace=False)
    print(f"\nvasl_scene wrote {out} in {time.monotonic() - t0:.1f} s\n{r.stdout}")
    return out


@pytest.fixture(scope="session")
def server(tmp_path_factory):
    base = tmp_path_factory.mktemp("vasld")
    data_dir = str(base / "data")
    port_file = str(base / "port")
    log_path = str(base / "vasld.log")
    log = open(log_path, "w")
    proc = subprocess.Popen([_require(VASLD), "--address", "127.0.0.1:0", "--data-dir", data_dir,
                             "--port-file", port_file],
                            stdout=log, stderr=subprocess.STDOUT)
    try:
        address = _port_file_address(port_file, proc, log_path)
        _wait_serving(address, proc, log_path)
        yield Server(proc, address, data_dir, log_path)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        log.close()
        with open(log_path, errors="replace") as f:
            tail = f.read().splitlines()[-5:]
        print("\nvasld log tail:\n" + "\n".join(tail))


@pytest.fixture(scope="session")
def client(server):
    from vasl import Client

    with Client(server.address, timeout_s=600) as c:
        yield c


def manifests(scene: str):
    return sorted(glob.glob(os.path.join(scene, "scan-*.json")))


@pytest.fixture(scope="session")
def ingested(client, scene_dir):
    """Project e2e (0.05 m vossels) with every scan of the scene ingested; the ingest results."""
    client.create_project(E2E_PROJECT, vossel_size_m=VOSSEL_M, description="end-to-end test")
    results = []
    for m in manifests(scene_dir):
        t0 = time.monotonic()
        r = client.ingest(E2E_PROJECT, m)
        print(f"\ningested {r.scan}: version {r.version}, {r.point_count} points, "
              f"{r.vossel_count} vossels, {r.record_count} records, "
              f"{time.monotonic() - t0:.1f} s; stages {r.stages}")
        results.append(r)
    return results


@pytest.fixture(scope="session")
def views(scene_dir):
    with open(os.path.join(scene_dir, "truth", "views.json")) as f:
        return {v["name"]: v for v in json.load(f)["views"]}


def run_cli(server, *args, check=True):
    """Runs `vasl --server ADDRESS ARGS...` and returns the CompletedProcess; with `check`,
    asserts it exited 0 (showing its output if not)."""
    r = subprocess.run([sys.executable, "-m", "vasl.cli", "--server", server.address, *args],
                       capture_output=True, text=True, timeout=600)
    if check:
        assert r.returncode == 0, f"vasl {' '.join(args)} exited {r.returncode}:\n{r.stdout}\n{r.stderr}"
    return r
