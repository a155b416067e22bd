"""vasld serves gRPC health checking and server reflection, and logs one line per request."""
from __future__ import annotations

import re

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc


def test_health_serving(server):
    with grpc.insecure_channel(server.address) as channel:
        stub = health_pb2_grpc.HealthStub(channel)
        r = stub.Check(health_pb2.HealthCheckRequest(service=""), timeout=5)
        print(f"\nhealth: {health_pb2.HealthCheckResponse.ServingStatus.Name(r.status)}")
        assert r.status == health_pb2.HealthCheckResponse.SERVING


def _reflection(channel, module):
    pb2 = __import__(f"grpc_reflection.{module}.reflection_pb2", fromlist=["x"])
    pb2_grpc = __import__(f"grpc_reflection.{module}.reflection_pb2_grpc", fromlist=["x"])
    stub = pb2_grpc.ServerReflectionStub(channel)
    reqs = [pb2.ServerReflectionRequest(list_services=""),
            pb2.ServerReflectionRequest(file_containing_symbol="vasl.v1.VaslService")]
    return list(stub.ServerReflectionInfo(iter(reqs), timeout=10))


def test_reflection_lists_the_service(server):
    with grpc.insecure_channel(server.address) as channel:
        try:
            responses = _reflection(channel, "v1alpha")  # what Debian's gRPC 1.51 serves
        except grpc.RpcError as e:
            assert e.code() == grpc.StatusCode.UNIMPLEMENTED
            responses = _reflection(channel, "v1")
    services = [s.name for s in responses[0].list_services_response.service]
    print(f"\nreflection services: {services}")
    assert "vasl.v1.VaslService" in services
    assert "grpc.health.v1.Health" in services
    files = responses[1].file_descriptor_response.file_descriptor_proto
    assert files, "file_containing_symbol returned no descriptor"
    from google.protobuf import descriptor_pb2

    fd = descriptor_pb2.FileDescriptorProto.FromString(files[0])
    assert fd.package == "vasl.v1"
    assert "Render" in [m.name for m in fd.service[0].method]


def test_request_log_lines(server, client):
    client.list_projects()
    lines = [l for l in server.log().splitlines() if "ListProjects" in l]
    print("\n" + (lines[-1] if lines else "(none)"))
    assert lines and re.search(r"ListProjects project=- code=OK ms=\d+\.\d", lines[-1])


def test_list_calls_page_and_times_are_timestamps(server, client, ingested):
    """Every List RPC pages with a token that survives changes between calls; times are
    google.protobuf.Timestamp (the client shows them as RFC 3339)."""
    from vasl._proto import vasl_pb2 as pb

    for name in ("page-a", "page-b", "page-c"):
        client.create_project(name, vossel_size_m=0.1)
    everything = [p.name for p in client.list_projects()]
    assert everything == sorted(everything) and {"page-a", "page-b", "page-c"} <= set(everything)
    assert [p.name for p in client.list_projects(page_size=1)] == everything
    first = client.stub.ListProjects(pb.ListProjectsRequest(page_size=2))
    assert len(first.projects) == 2 and first.next_page_token
    rest = client.stub.ListProjects(pb.ListProjectsRequest(page_size=1000,
                                                           page_token=first.next_page_token))
    assert [p.name for p in first.projects] + [p.name for p in rest.projects] == everything
    assert rest.next_page_token == ""
    try:
        client.stub.ListProjects(pb.ListProjectsRequest(page_token="bogus"))
        raise AssertionError("a bogus page token was accepted")
    except grpc.RpcError as e:
        assert e.code() == grpc.StatusCode.INVALID_ARGUMENT, e
    from conftest import E2E_PROJECT
    project = E2E_PROJECT
    assert ingested
    scans = client.list_scans(project, page_size=1)
    assert [s.name for s in scans] == [s.name for s in client.list_scans(project)]
    assert len(scans) >= 2
    assert all(re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d(\.\d+)?Z", s.created_utc) for s in scans)
    assert all(s.captured_utc.startswith("2026-") for s in scans), [s.captured_utc for s in scans]
    versions = client.list_versions(project, page_size=1)
    assert [v.version for v in versions] == [v.version for v in client.list_versions(project)]
    assert all(v.created_utc.endswith("Z") for v in versions)
    raw = client.stub.GetProject(pb.GetProjectRequest(project=project))
    assert raw.HasField("create_time") and raw.create_time.seconds > 1.7e9


def test_a_second_vasld_on_a_served_port_refuses_to_start(server, tmp_path):
    """gRPC's SO_REUSEPORT is off: a second server on the same address fails to bind, rather
    than sharing connections with the first."""
    import subprocess

    from conftest import VASLD

    r = subprocess.run([VASLD, "--address", server.address, "--data-dir", str(tmp_path / "d2")],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode != 0, r.stdout + r.stderr
    assert "cannot listen" in r.stderr, r.stderr
