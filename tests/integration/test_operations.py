"""Changes sent under a request id are done once (issue "Reliability and security": long-running
operations, idempotent retries). A retry of a committed ingest is answered from its commit with
no new version, also after the server is killed and restarted; a call cancelled (or whose
deadline passes) while the server works stops the change before its commit, and
GetOperation tells the client what became of it; an id cannot name a second change."""
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

            # A call cancelled while the server works: the change stops at its next stage,
            # commits nothing, and GetOperation says so; a retry under the id runs it whole.
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
            assert done["state"] == "failed", done
            assert done["error_code"] == grpc.StatusCode.CANCELLED.value[0], done
            assert "cancelled" in done["error_message"], done
            assert [v.version for v in client.list_versions("ops")] == [first.version]
            assert [s.name for s in client.list_scans("ops")] == [first.scan]
            retried = client.ingest("ops", scans[1], request_id="scan-2-cut")
            assert not retried.replayed and retried.version == first.version + 1
            assert retried.record_count > first.record_count
            print(f"cancelled at stage {op['stage']!r}: stopped ({done['error_message']}); "
                  f"the retry committed version {retried.version}, "
                  f"{retried.record_count} records")

            # A deadline that passes while the server works stops the change the same way;
            # the client resolves the lost answer through GetOperation and sends it again.
            short = Client(address, timeout_s=0.2)
            try:
                t0 = time.monotonic()
                with pytest.raises(VaslError) as e:
                    short.ingest("ops", scans[2], request_id="scan-3-late", retries=0)
                assert e.value.code == grpc.StatusCode.DEADLINE_EXCEEDED, e.value.details
            finally:
                short.close()
            late = client.wait_operation("ops", "scan-3-late", timeout_s=120, poll_s=0.1,
                                         missing_ok=True)
            if late is not None:  # the header arrived: the server stopped the work (while
                # it ran: DEADLINE_EXCEEDED; while the bytes still came: the cut stream)
                assert late["state"] == "failed", late
                assert late["error_code"] in (grpc.StatusCode.DEADLINE_EXCEEDED.value[0],
                                              grpc.StatusCode.CANCELLED.value[0]), late
            assert client.list_versions("ops")[-1].version == retried.version
            print(f"deadline of 0.2 s: DEADLINE_EXCEEDED after {time.monotonic() - t0:.2f} s, "
                  f"operation {late['state'] + ': ' + late['error_message'] if late else 'never started'}, "
                  "no version made")

            # A reweight under a request id is done once too.
            client.create_profile("ops", {"name": "far", "proximity_m": 4.0})
            rw = client.reweight("ops", "far", request_id="reweight-far-1")
            assert not rw.replayed and rw.version == retried.version + 1
            rw_again = client.reweight("ops", "far", request_id="reweight-far-1")
            assert rw_again.replayed and rw_again.version == rw.version
            op = client.get_operation("ops", "reweight-far-1")
            assert op["kind"] == "reweight" and op["subject"] == "far@latest"
            assert op["reweight"].tile_count == rw.tile_count
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


def test_renders_are_not_held_up_by_a_running_change(tmp_path, scene_dir):
    """Changes run on a pool of their own (--change-workers): with one read worker and one
    change worker, renders asked while a rebuild runs are answered before it ends, and a second
    change waits its turn instead of taking the readers' thread."""
    import concurrent.futures

    data = str(tmp_path / "data")
    os.makedirs(data)
    scans = manifests(scene_dir)
    proc, address, log = start_vasld(VASLD, str(tmp_path), data, 0,
                                     ("--workers", "1", "--change-workers", "1"))
    try:
        with Client(address, timeout_s=300) as client:
            client.create_project("busy", vossel_size_m=VOSSEL_M)
            for m in scans:
                client.ingest("busy", m)
            pose = Pose.parse(read_manifest(scans[0]).pose)
            with concurrent.futures.ThreadPoolExecutor(2) as pool:
                rebuild = pool.submit(client.rebuild, "busy", request_id="busy-rebuild")
                deadline = time.monotonic() + 60
                while time.monotonic() < deadline:
                    try:
                        if client.get_operation("busy", "busy-rebuild")["state"] == "running":
                            break
                    except VaslError:
                        pass
                    time.sleep(0.01)
                seconds = []
                for _ in range(5):
                    t0 = time.monotonic()
                    r = client.render("busy", pose, 64, 32, formats=("exr",))
                    seconds.append(time.monotonic() - t0)
                    assert r.rgb.shape == (32, 64, 3)
                still = client.get_operation("busy", "busy-rebuild")
                assert still["state"] == "running", (
                    f"the renders waited for the rebuild: {still['state']}")
                rebuilt = rebuild.result(timeout=300)
            assert not rebuilt.replayed
            print(f"5 renders of 64x32 during a rebuild ({rebuilt.seconds:.2f} s): "
                  f"{max(seconds) * 1e3:.0f} ms the slowest; the rebuild still ran after them")
    finally:
        proc.terminate()
        proc.wait(timeout=60)
        log.close()
