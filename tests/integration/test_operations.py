"""Changes sent under a request id are done once (issue "Reliability and security": long-running
operations, idempotent retries). A retry of a committed ingest is answered from its commit with
no new version, also after the server is killed and restarted; a call cancelled while the
server works leaves the change running to its commit, and GetOperation tells the client what
became of it; an id cannot name a second change."""
from __future__ import annotations

import os
import signal
import time

import grpc
import pytest

from crash_util import start_vasld
from conftest import VASLD, VOSSEL_M, manifests
from vasl import Client, VaslError
from vasl._proto import vasl_pb2 as pb
from vasl.readers import read_manifest, read_ply
from vasl.client import ingest_requests, pack_points, pose_to_pb
from vasl.types import Pose


def _header_and_payload(manifest: str, project: str, request_id: str):
    """The IngestScan stream of a manifest, built as the client builds it."""
    m = read_manifest(manifest)
    cloud = read_ply(m.points_path)
    header = pb.ScanHeader(project=project, scan=m.scan, pose=pose_to_pb(Pose.parse(m.pose)),
                           request_id=request_id)
    header.lidar.divergence_rad = m.divergence_rad
    header.lidar.point_format = pb.POINT_FORMAT_XYZI_F32LE
    points = pack_points(cloud.xyz_m, cloud.intensity, None)
    header.lidar.point_count = len(points) // 16
    images = []
    for p in m.panoramas:
        with open(p.image_path, "rb") as f:
            images.append(f.read())
        header.panoramas.add(name=p.name, modality=pb.MODALITY_RGB,
                             pose=pose_to_pb(Pose.parse(p.pose)), encoded_size_bytes=len(images[-1]))
    return header, points, images


def test_retries_under_a_request_id_are_answered_from_the_commit(tmp_path, scene_dir):
    data = str(tmp_path / "data")
    os.makedirs(data)
    scans = manifests(scene_dir)
    proc, address, log = start_vasld(VASLD, str(tmp_path), data, 0)
    try:
        with Client(address, timeout_s=120) as client:
            client.create_project("ops", vossel_size_m=VOSSEL_M)
            first = client.ingest("ops", scans[0], request_id="scan-1-try")
            assert first.request_id == "scan-1-try" and not first.replayed
            again = client.ingest("ops", scans[0], request_id="scan-1-try")
            assert again.replayed
            assert (again.version, again.scan_id, again.vossel_count, again.record_count) == (
                first.version, first.scan_id, first.vossel_count, first.record_count)
            assert [v.version for v in client.list_versions("ops")] == [first.version]
            op = client.get_operation("ops", "scan-1-try")
            assert op["state"] == "succeeded" and op["kind"] == "ingest"
            assert op["subject"] == first.scan and op["version"] == first.version
            assert op["ingest"].record_count == first.record_count

            # The id names one change: another scan under it is refused, nothing is stored.
            with pytest.raises(VaslError) as e:
                client.ingest("ops", scans[1], request_id="scan-1-try", retries=0)
            assert e.value.code == grpc.StatusCode.FAILED_PRECONDITION
            assert "scan-1-try" in e.value.details and "new request id" in e.value.details
            for bad, code in (("no such id", grpc.StatusCode.INVALID_ARGUMENT),
                              ("never-sent", grpc.StatusCode.NOT_FOUND)):
                with pytest.raises(VaslError) as e:
                    client.get_operation("ops", bad)
                assert e.value.code == code, e.value.details
            print(f"retry: version {again.version} replayed, "
                  f"{len(client.list_versions('ops'))} version(s) kept")

            # A call cancelled while the server works: the change goes on to its commit and
            # GetOperation says so; the retry is answered from it.
            header, points, images = _header_and_payload(scans[1], "ops", "scan-2-cut")
            future = client.stub.IngestScan.future(
                ingest_requests(header, points, images, client.chunk_bytes), timeout=120)
            stages = []
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                try:
                    op = client.get_operation("ops", "scan-2-cut")
                except VaslError:
                    time.sleep(0.02)
                    continue
                stages.append(op["stage"])
                if op["state"] == "running" and op["stage"] not in ("received",):
                    break
                time.sleep(0.02)
            assert op["state"] == "running", stages
            future.cancel()
            done = client.wait_operation("ops", "scan-2-cut", timeout_s=120, poll_s=0.1)
            assert done["state"] == "succeeded", done
            assert done["version"] == first.version + 1
            assert [s.name for s in client.list_scans("ops")] == [first.scan, header.scan]
            retried = client.ingest("ops", scans[1], request_id="scan-2-cut")
            assert retried.replayed and retried.version == done["version"]
            assert retried.record_count == done["ingest"].record_count > first.record_count
            print(f"cancelled at stage {op['stage']!r}: committed version {done['version']}, "
                  f"{done['ingest'].record_count} records; retry replayed")
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=60)
        log.close()

    # Killed and restarted: the commit and its answer are in the catalog.
    proc, address, log = start_vasld(VASLD, str(tmp_path), data, 1)
    try:
        with Client(address, timeout_s=120) as client:
            op = client.get_operation("ops", "scan-1-try")
            assert op["state"] == "succeeded" and op["version"] == first.version
            assert op["ingest"].vossel_count == first.vossel_count
            again = client.ingest("ops", scans[0], request_id="scan-1-try")
            assert again.replayed and again.version == first.version
            rebuilt = client.rebuild("ops", request_id="rebuild-1")
            assert not rebuilt.replayed
            assert client.rebuild("ops", request_id="rebuild-1").version == rebuilt.version
            assert client.list_versions("ops")[-1].version == rebuilt.version
    finally:
        proc.terminate()
        proc.wait(timeout=60)
        log.close()
