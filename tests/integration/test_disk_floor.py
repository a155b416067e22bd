"""A server whose data disk is below its free-space floor refuses every call that would write
project data (ingest, back-projection, write-role RPCs, CreateProject) with RESOURCE_EXHAUSTED
before reading the upload, writes nothing, and keeps serving reads. The floor is the real
check against the real file system: set above any disk's size, it is always below it."""
from __future__ import annotations

import os

import grpc
import pytest

from crash_util import start_vasld
from conftest import VASLD, VOSSEL_M, manifests
from vasl import Client, VaslError

FLOOR = str(1 << 62)  # 4 EiB: more than any file system here has free


def _files(root):
    return sorted(os.path.relpath(os.path.join(d, f), root)
                  for d, _, files in os.walk(root) for f in files if "-wal" not in f and "-shm" not in f)


def test_writes_are_refused_below_the_disk_floor(tmp_path, scene_dir):
    data = str(tmp_path / "data")
    os.makedirs(data)
    scans = manifests(scene_dir)
    # First a project with one scan, written under no floor.
    proc, address, log = start_vasld(VASLD, str(tmp_path), data, 0, ("--min-free-disk-bytes", "0"))
    try:
        with Client(address, timeout_s=120) as client:
            client.create_project("full", vossel_size_m=VOSSEL_M)
            client.ingest("full", scans[0])
    finally:
        proc.terminate()
        proc.wait(timeout=60)
        log.close()
    before = _files(data)

    proc, address, log = start_vasld(VASLD, str(tmp_path), data, 1, ("--min-free-disk-bytes", FLOOR))
    try:
        client = Client(address, timeout_s=120)
        refused = {}
        calls = {
            "IngestScan": lambda: client.ingest("full", scans[1]),
            "CreateProject": lambda: client.create_project("another", vossel_size_m=VOSSEL_M),
            "Rebuild": lambda: client.rebuild("full"),
        }
        for name, call in calls.items():
            with pytest.raises(VaslError) as e:
                call()
            refused[name] = (e.value.code, e.value.details)
        for name, (code, details) in refused.items():
            print(f"{name}: {code.name}: {details}")
            assert code == grpc.StatusCode.RESOURCE_EXHAUSTED, f"{name}: {code.name}: {details}"
            assert "--min-free-disk-bytes" in details and "nothing was written" in details
            assert data not in details
        # Reads still work, and nothing was written.
        assert client.health() == "SERVING"
        render = client.render("full", [1.0, 1.0, 1.2], 64, 32, formats=("exr",))
        assert render.hit_pixels > 0
        assert len(client.list_scans("full")) == 1
    finally:
        proc.terminate()
        proc.wait(timeout=60)
        log.close()
    after = [f for f in _files(data) if not f.startswith("port-") and not f.endswith(".log")]
    print(f"{len(before)} files before, {len(after)} after")
    assert after == before
