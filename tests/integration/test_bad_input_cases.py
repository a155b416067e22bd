"""Bad input over every RPC (issue "Reliability and security"): each case gets the right code
and a message that names the problem and no server path; the project's files are byte-identical
afterwards (the catalog compared by content); the server keeps serving."""
from __future__ import annotations

import hashlib
import os
import sqlite3

import grpc
import numpy as np
import pytest

from conftest import E2E_PROJECT
from synth_scans import png_bytes
from vasl import pack_points
from vasl._proto import vasl_pb2 as pb
from vasl.client import ingest_requests, pose_to_pb
from vasl.types import Pose

P = E2E_PROJECT
BAD = grpc.StatusCode.INVALID_ARGUMENT
LIMIT = grpc.StatusCode.RESOURCE_EXHAUSTED
MISSING = grpc.StatusCode.NOT_FOUND


def _pose(x=0.0, y=0.0, z=1.0, q=(0.0, 0.0, 0.0, 1.0)):
    return pose_to_pb(Pose((x, y, z), q)) if all(map(np.isfinite, (x, y, z, *q))) and any(q) else \
        pb.Pose(position_m=pb.Vec3(x=x, y=y, z=z),
                quaternion_xyzw=pb.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))


def _header(scan="bad-case", points=4, images=(), pose=None, fmt=pb.POINT_FORMAT_XYZI_F32LE):
    h = pb.ScanHeader(project=P, scan=scan, rig="test", pose=pose or _pose())
    h.lidar.divergence_rad = 3e-4
    h.lidar.point_format = fmt
    h.lidar.point_count = points
    for i, n in enumerate(images):
        h.panoramas.add(name=f"cam{i}", modality=pb.MODALITY_RGB, pose=_pose(),
                        encoded_size_bytes=n)
    return h


def _unknown_project_header():
    h = _header()
    h.project = "no-such-project"
    return h


def _points(n=4, bad=None):
    xyz = np.random.default_rng(3).uniform(-3, 3, size=(n, 3))
    if bad is not None:
        xyz[1, 0] = bad
    return pack_points(xyz, np.full(n, 0.5))


def _png(width, height, rows=1):
    """A PNG whose header claims width x height, with `rows` rows of data (a pixel bomb)."""
    return png_bytes(width, height, b"".join(b"\0" + b"\0" * (3 * width) for _ in range(rows)))


def _ingest(header, point_bytes, images=()):
    return lambda stub: stub.IngestScan(ingest_requests(header, point_bytes, images), timeout=60)


def _stream(*messages):
    return lambda stub: stub.IngestScan(iter(messages), timeout=60)


def _render(**fields):
    def call(stub):
        r = pb.RenderRequest(project=P, width_px=64, height_px=32)
        r.pose.CopyFrom(_pose())
        for k, v in fields.items():
            if k == "pose":
                r.pose.CopyFrom(v)
            else:
                setattr(r, k, v)
        return list(stub.Render(r, timeout=60))
    return call


def _backproject(header, data=b""):
    def call(stub):
        msgs = [pb.BackProjectRequest(header=header)]
        msgs += [pb.BackProjectRequest(image_chunk=data[i:i + 65536])
                 for i in range(0, len(data), 65536)]
        return stub.BackProject(iter(msgs), timeout=60)
    return call


def _unary(method, request):
    return lambda stub: getattr(stub, method)(request, timeout=60)


BOMB = _png(100_000, 100_000)
CASES = [
    # IngestScan: poses, points, sizes, order, truncation, images, names
    ("ingest NaN pose", _ingest(_header(pose=_pose(x=float("nan"))), _points()), {BAD}),
    ("ingest inf pose", _ingest(_header(pose=_pose(z=float("inf"))), _points()), {BAD}),
    ("ingest zero quaternion", _ingest(_header(pose=_pose(q=(0, 0, 0, 0))), _points()), {BAD}),
    ("ingest NaN point", _ingest(_header(), _points(bad=float("nan"))), {BAD}),
    ("ingest inf point", _ingest(_header(), _points(bad=float("inf"))), {BAD}),
    ("ingest zero points", _ingest(_header(points=0), b""), {BAD}),
    ("ingest huge point count", _ingest(_header(points=10**12), _points()), {LIMIT}),
    ("ingest negative point count", _ingest(_header(points=-5), _points()), {BAD}),
    ("ingest huge image size", _ingest(_header(images=[1 << 40]), _points()), {LIMIT}),
    ("ingest zero image size", _ingest(_header(images=[0]), _points()), {BAD}),
    ("ingest points before header", _stream(pb.IngestScanRequest(
        points=pb.PointsChunk(data=_points())), pb.IngestScanRequest(header=_header())), {BAD}),
    ("ingest two headers", _stream(pb.IngestScanRequest(header=_header()),
                                   pb.IngestScanRequest(header=_header())), {BAD}),
    ("ingest truncated points", _ingest(_header(points=8), _points(4)), {BAD}),
    ("ingest more points than declared", _ingest(_header(points=2), _points(4)), {BAD}),
    ("ingest truncated image", _ingest(_header(images=[1000]), _points(), [b"\x89PNG" * 10]),
     {BAD}),
    ("ingest image that does not decode", _ingest(_header(images=[64]), _points(), [b"x" * 64]),
     {BAD}),
    ("ingest pixel bomb", _ingest(_header(images=[len(BOMB)]), _points(), [BOMB]), {LIMIT, BAD}),
    ("ingest unknown point format", _ingest(_header(fmt=99), _points()), {BAD}),
    ("ingest empty scan name", _ingest(_header(scan=""), _points()), {BAD}),
    ("ingest newline in scan name", _ingest(_header(scan="a\nb"), _points()), {BAD}),
    ("ingest oversized scan name", _ingest(_header(scan="s" * 10000), _points()), {BAD}),
    ("ingest unknown project", _ingest(_unknown_project_header(), _points()), {MISSING}),
    # Projects
    ("create newline in name", _unary("CreateProject", pb.CreateProjectRequest(
        name="a\nb", vossel_size_m=0.1)), {BAD}),
    ("create oversized name", _unary("CreateProject", pb.CreateProjectRequest(
        name="p" * 5000, vossel_size_m=0.1)), {BAD}),
    ("create NaN vossel", _unary("CreateProject", pb.CreateProjectRequest(
        name="nan-vossel", vossel_size_m=float("nan"))), {BAD}),
    ("create negative vossel", _unary("CreateProject", pb.CreateProjectRequest(
        name="neg-vossel", vossel_size_m=-1)), {BAD}),
    ("create oversized description", _unary("CreateProject", pb.CreateProjectRequest(
        name="long-description", vossel_size_m=0.1, description="d" * 100000)), {BAD}),
    ("create duplicate", _unary("CreateProject", pb.CreateProjectRequest(
        name=P, vossel_size_m=0.1)), {grpc.StatusCode.ALREADY_EXISTS}),
    ("get path traversal", _unary("GetProject", pb.GetProjectRequest(project="../etc")), {BAD}),
    # Render
    ("render zero size", _render(width_px=0, height_px=0), {BAD}),
    ("render huge size", _render(width_px=10**6, height_px=10**6), {LIMIT}),
    ("render NaN pose", _render(pose=_pose(y=float("nan"))), {BAD}),
    ("render unknown profile", _render(profile="no-such-profile"), {MISSING}),
    ("render unknown version", _render(version=10**6), {MISSING}),
    # Profiles, reweight, records
    ("profile missing", _unary("CreateProfile", pb.CreateProfileRequest(project=P)), {BAD}),
    ("profile NaN alpha", _unary("CreateProfile", pb.CreateProfileRequest(
        project=P, profile=pb.WeightingProfile(name="nan-alpha", alpha=float("nan")))), {BAD}),
    ("profile newline in name", _unary("CreateProfile", pb.CreateProfileRequest(
        project=P, profile=pb.WeightingProfile(name="a\nb"))), {BAD}),
    ("reweight unknown profile", _unary("Reweight", pb.ReweightRequest(
        project=P, profile="no-such-profile")), {MISSING}),
    ("reweight negative revision", _unary("Reweight", pb.ReweightRequest(
        project=P, revision=-1)), {BAD}),
    ("activate unknown profile", _unary("SetActiveProfile", pb.SetActiveProfileRequest(
        project=P, name="no-such-profile")), {MISSING}),
    ("records without a point", _unary("QueryRecords", pb.QueryRecordsRequest(project=P)),
     {BAD}),
    ("records NaN box", _unary("QueryRecords", pb.QueryRecordsRequest(
        project=P, min_m=pb.Vec3(x=float("nan"))), ), {BAD}),
    # Versions and scans
    ("delete unknown scan", _unary("DeleteScan", pb.DeleteScanRequest(project=P, scan="nope")),
     {MISSING}),
    ("rollback to a future version", _unary("Rollback", pb.RollbackRequest(
        project=P, version=10**6)), {MISSING, BAD, grpc.StatusCode.FAILED_PRECONDITION}),
    ("pin unknown version", _unary("PinVersion", pb.PinVersionRequest(project=P, version=10**6)),
     {MISSING}),
    ("export unknown version", lambda stub: list(stub.Export(pb.ExportRequest(
        project=P, version=10**6), timeout=60)), {MISSING}),
    ("inspect negative version", _unary("InspectRecords", pb.InspectRecordsRequest(
        project=P, version=-1)), {BAD}),
    # Text fields: every string of every request is bounded and printable before any handler
    # reads it (server/request_check.h), and a refusal never echoes it.
    ("delete newline in scan name", _unary("DeleteScan", pb.DeleteScanRequest(
        project=P, scan="a\nb")), {BAD}),
    ("delete oversized scan name", _unary("DeleteScan", pb.DeleteScanRequest(
        project=P, scan="s" * 100000)), {BAD}),
    ("get NUL in project", _unary("GetProject", pb.GetProjectRequest(project="a\x00b")), {BAD}),
    ("get oversized project", _unary("GetProject", pb.GetProjectRequest(project="p" * 100000)),
     {BAD}),
    ("render oversized profile", _render(profile="p" * 5000), {BAD}),
    ("reweight escape sequence in profile", _unary("Reweight", pb.ReweightRequest(
        project=P, profile="\x1b]0;owned\x07")), {BAD}),
    ("list projects oversized page token", _unary("ListProjects", pb.ListProjectsRequest(
        page_token="t" * 5000)), {BAD}),
    ("revoke escape sequence in token id", _unary("RevokeToken", pb.RevokeTokenRequest(
        id="\x1b[2J")), {BAD}),
    ("backproject newline in batch name", _backproject(pb.BackProjectHeader(
        project=P, name="a\nb", pose=_pose(), image_size_bytes=4), b"abcd"), {BAD}),
    # BackProject
    ("backproject no pose", _backproject(pb.BackProjectHeader(project=P, image_size_bytes=4),
                                         b"abcd"), {BAD}),
    ("backproject zero size", _backproject(pb.BackProjectHeader(project=P, pose=_pose())),
     {BAD}),
    ("backproject malformed EXR", _backproject(pb.BackProjectHeader(
        project=P, pose=_pose(), image_size_bytes=4096), b"v/1\x01" + b"\0" * 4092), {BAD}),
    ("backproject truncated", _backproject(pb.BackProjectHeader(
        project=P, pose=_pose(), image_size_bytes=4096), b"\0" * 100), {BAD}),
    ("backproject NaN pose", _backproject(pb.BackProjectHeader(
        project=P, pose=_pose(x=float("nan")), image_size_bytes=4), b"abcd"), {BAD}),
]


def _project_state(data_dir: str):
    """Every file of the project (the catalog by content: its rows), hashed."""
    root = os.path.join(data_dir, P)
    state = {}
    for dirpath, _, files in os.walk(root):
        for name in files:
            path = os.path.join(dirpath, name)
            rel = os.path.relpath(path, root)
            if rel.startswith("catalog.sqlite"):
                continue
            with open(path, "rb") as f:
                state[rel] = hashlib.sha256(f.read()).hexdigest()
    db = sqlite3.connect(f"file:{os.path.join(root, 'catalog.sqlite')}?mode=ro", uri=True)
    try:
        rows = "\n".join(line for line in db.iterdump() if "renders" not in line)
    finally:
        db.close()
    state["catalog rows"] = hashlib.sha256(rows.encode()).hexdigest()
    return state


@pytest.fixture(scope="module")
def before(server, client, ingested):
    return _project_state(server.data_dir)


@pytest.mark.parametrize("name,call,codes", CASES, ids=[c[0] for c in CASES])
def test_bad_input_case(server, client, before, name, call, codes):
    with pytest.raises(grpc.RpcError) as e:
        call(client.stub)
    code, details = e.value.code(), e.value.details() or ""
    print(f"\n{name}: {code.name}: {details[:200]}")
    assert code in codes, f"{name}: {code.name}: {details}"
    assert details, "the message must say what is wrong"
    assert len(details) < 2048, f"the message is {len(details)} bytes: it echoes the input"
    assert not any(ord(c) < 0x20 or ord(c) == 0x7f for c in details), \
        f"the message carries a control character: {details!r}"
    assert server.data_dir not in details, f"the message shows a server path: {details}"
    assert _project_state(server.data_dir) == before, f"{name} changed the project's files"


def test_server_still_serves_after_every_case(server, client, before):
    print(f"\n{len(CASES)} bad-input cases over IngestScan, CreateProject, GetProject, Render, "
          f"CreateProfile, Reweight, SetActiveProfile, QueryRecords, DeleteScan, Rollback, "
          f"PinVersion, Export, InspectRecords, ListProjects, RevokeToken and BackProject")
    assert client.health() == "SERVING"
    r = client.render(P, [2.0, 2.0, 1.5], 64, 32, formats=("exr",))
    assert r.hit_pixels > 0
    assert _project_state(server.data_dir) == before


def test_a_damaged_project_is_reported_and_the_others_listed(server, client, ingested):
    broken = os.path.join(server.data_dir, "broken-site")
    os.makedirs(broken)
    try:
        with open(os.path.join(broken, "catalog.sqlite"), "wb") as f:
            f.write(b"this is not an SQLite database" * 100)
        projects = {p.name: p for p in client.list_projects()}
        print(f"\nListProjects with a damaged project: {sorted(projects)}; broken-site: "
              f"{projects['broken-site'].problem}")
        assert projects["broken-site"].problem, "the damaged project is not reported as such"
        assert E2E_PROJECT in projects and not projects[E2E_PROJECT].problem
        assert projects[E2E_PROJECT].scan_count == len(ingested)
        assert server.data_dir not in projects["broken-site"].problem
        with pytest.raises(grpc.RpcError) as e:
            client.stub.GetProject(pb.GetProjectRequest(project="broken-site"), timeout=30)
        assert server.data_dir not in (e.value.details() or "")
    finally:
        import shutil
        shutil.rmtree(broken)
