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
