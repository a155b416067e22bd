"""Bad input is INVALID_ARGUMENT (NOT_FOUND for an unknown project) and never changes a project
(ARCHITECTURE.md "Errors and limits"): same HEAD version and scan count afterwards."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import grpc
import numpy as np
import pytest

from conftest import E2E_PROJECT
from vasl import Client, VaslError, pack_points, read_manifest, read_ply
from vasl._proto import vasl_pb2 as pb
from vasl.client import ingest_requests, pose_to_pb
from vasl.types import Pose


@pytest.fixture
def unchanged(client, ingested):
    before = client.get_project(E2E_PROJECT)
    yield
    after = client.get_project(E2E_PROJECT)
    assert (after.head_version, after.scan_count, after.record_count) == \
        (before.head_version, before.scan_count, before.record_count)


def _header(scan="bad-scan", points=4, image_bytes=()):
    h = pb.ScanHeader(project=E2E_PROJECT, scan=scan, rig="test",
                      pose=pose_to_pb(Pose((0.0, 0.0, 1.0), (0.0, 0.0, 0.0, 1.0))))
    h.lidar.divergence_rad = 3e-4
    h.lidar.point_format = pb.POINT_FORMAT_XYZI_F32LE
    h.lidar.point_count = points
    for i, n in enumerate(image_bytes):
        h.panoramas.add(name=f"cam{i}", modality=pb.MODALITY_RGB,
                        pose=pose_to_pb(Pose((0.0, 0.0, 1.0), (0.0, 0.0, 0.0, 1.0))),
                        encoded_size_bytes=n)
    return h


def _points(n=4):
    rng = np.random.default_rng(3)
    return pack_points(rng.uniform(-3, 3, size=(n, 3)), rng.uniform(0, 1, size=n))


def _expect(code, fn):
    with pytest.raises(VaslError) as e:
        fn()
    print(f"\n{e.value.method}: {e.value.code.name}: {e.value.details}")
    assert e.value.code == code, str(e.value)
    assert e.value.details, "the message must tell the user what to fix"
    return e.value


def test_nan_in_pose(client, unchanged):
    h = _header()
    h.pose.position_m.x = float("nan")
    err = _expect(grpc.StatusCode.INVALID_ARGUMENT, lambda: client.ingest_stream(h, _points(), []))
    assert "finite" in err.details
    # The typed client refuses it before sending.
    with pytest.raises(ValueError):
        client.ingest(E2E_PROJECT, scan="x", points=np.zeros((4, 3)),
                      pose=[float("nan"), 0, 0])


def test_image_that_does_not_decode(client, scene_dir, unchanged):
    m = read_manifest(os.path.join(scene_dir, "scan-1.json"))
    cloud = read_ply(m.points_path)
    _expect(grpc.StatusCode.INVALID_ARGUMENT, lambda: client.ingest(
        E2E_PROJECT, scan="garbage-image", points=cloud.xyz_m, intensity=cloud.intensity,
        pose=m.pose, panoramas=[{"name": "cam0", "image": b"this is not a PNG" * 64,
                                 "pose": m.panoramas[0].pose, "modality": "rgb"}]))
    # A real PNG cut short: the signature is right, the data does not decode.
    png = open(m.panoramas[0].image_path, "rb").read()
    _expect(grpc.StatusCode.INVALID_ARGUMENT, lambda: client.ingest(
        E2E_PROJECT, scan="truncated-image", points=cloud.xyz_m, intensity=cloud.intensity,
        pose=m.pose, panoramas=[{"name": "cam0", "image": png[:len(png) // 3],
                                 "pose": m.panoramas[0].pose, "modality": "rgb"}]))


def test_points_chunk_not_multiple_of_16(client, unchanged):
    def stream():
        yield pb.IngestScanRequest(header=_header(points=4))
        yield pb.IngestScanRequest(points=pb.PointsChunk(data=_points()[:17]))

    err = _expect(grpc.StatusCode.INVALID_ARGUMENT, lambda: _call_ingest(client, stream()))
    assert "multiple of 16" in err.details


def test_stream_without_header(client, unchanged):
    def points_only():
        yield pb.IngestScanRequest(points=pb.PointsChunk(data=_points()))

    err = _expect(grpc.StatusCode.INVALID_ARGUMENT, lambda: _call_ingest(client, points_only()))
    assert "ScanHeader" in err.details
    err = _expect(grpc.StatusCode.INVALID_ARGUMENT, lambda: _call_ingest(client, iter(())))
    assert "ScanHeader" in err.details


def test_byte_counts_and_undeclared_panorama(client, unchanged):
    # Fewer points than the header announces.
    _expect(grpc.StatusCode.INVALID_ARGUMENT,
            lambda: client.ingest_stream(_header(points=5), _points(4), []))
    # Image chunk for a panorama the header does not declare.
    def stream():
        yield pb.IngestScanRequest(header=_header(points=4))
        yield pb.IngestScanRequest(points=pb.PointsChunk(data=_points()))
        yield pb.IngestScanRequest(image=pb.ImageChunk(panorama_name="cam7", data=b"x"))

    err = _expect(grpc.StatusCode.INVALID_ARGUMENT, lambda: _call_ingest(client, stream()))
    assert "cam7" in err.details


def test_duplicate_scan_is_already_exists(client, scene_dir, unchanged):
    _expect(grpc.StatusCode.ALREADY_EXISTS,
            lambda: client.ingest(E2E_PROJECT, os.path.join(scene_dir, "scan-1.json")))


def test_unknown_project_is_not_found(client, scene_dir):
    _expect(grpc.StatusCode.NOT_FOUND, lambda: client.get_project("no-such-project"))
    _expect(grpc.StatusCode.NOT_FOUND, lambda: client.list_scans("no-such-project"))
    _expect(grpc.StatusCode.NOT_FOUND,
            lambda: client.render("no-such-project", [0, 0, 1], 64, 32))
    _expect(grpc.StatusCode.NOT_FOUND,
            lambda: client.ingest("no-such-project", os.path.join(scene_dir, "scan-1.json")))
    assert all(p.name != "no-such-project" for p in client.list_projects())


def test_render_size_limits(client, ingested):
    _expect(grpc.StatusCode.RESOURCE_EXHAUSTED,
            lambda: client.render(E2E_PROJECT, [0, 0, 1], 100000, 64, decode=False))
    h = pb.RenderRequest(project=E2E_PROJECT, width_px=0, height_px=0)
    h.pose.CopyFrom(pose_to_pb(Pose()))
    _expect(grpc.StatusCode.INVALID_ARGUMENT,
            lambda: _raise(lambda: list(client.stub.Render(h, timeout=30)), "Render"))


def test_cli_reports_error_and_exits_nonzero(server, client, scene_dir, tmp_path, unchanged):
    doc = json.load(open(os.path.join(scene_dir, "scan-1.json")))
    doc["scan"] = "cli-bad-image"
    (tmp_path / "bad.png").write_bytes(b"definitely not an image" * 10)
    doc["lidar"]["points"] = os.path.join(scene_dir, doc["lidar"]["points"])
    doc["panoramas"][0]["image"] = "bad.png"
    manifest = tmp_path / "bad.json"
    manifest.write_text(json.dumps(doc))
    r = subprocess.run([sys.executable, "-m", "vasl.cli", "--server", server.address, "ingest",
                        str(manifest), "--project", E2E_PROJECT, "--quiet"],
                       capture_output=True, text=True)
    print(f"\nCLI exit {r.returncode}: {r.stderr.strip()}")
    assert r.returncode == 1
    assert "INVALID_ARGUMENT" in r.stderr and "vasl: error:" in r.stderr
    r = subprocess.run([sys.executable, "-m", "vasl.cli", "--server", server.address, "project",
                        "get", "no-such-project"], capture_output=True, text=True)
    assert r.returncode == 1 and "NOT_FOUND" in r.stderr


def _raise(fn, method):
    try:
        return fn()
    except grpc.RpcError as e:
        raise VaslError(e.code(), e.details(), method) from None


def _call_ingest(client, requests):
    return _raise(lambda: client.stub.IngestScan(requests, timeout=60), "IngestScan")
