"""Access control and TLS end to end (issue "Reliability and security"): every RPC of
vasl.v1.VaslService under every role, on a vasld with an admin token, in plaintext and over
mutual TLS. Health stays open; reflection describes every listed service; the token store keeps
hashes only; a vasld on a non-loopback address without access control refuses to start."""
from __future__ import annotations

import os
import signal
import sqlite3
import subprocess

import grpc
import pytest

from conftest import VASLD, _port_file_address, _require

ADMIN_TOKEN = "vasl-admin-test-token-0123456789"
PROJECT = "acl"
OTHER = "acl-other"
DENIED = {grpc.StatusCode.UNAUTHENTICATED, grpc.StatusCode.PERMISSION_DENIED}


def _openssl(*args, cwd):
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


def make_certs(d: str) -> dict:
    """A CA, a server certificate for 127.0.0.1/localhost and a client certificate (EC P-256)."""
    def key(name):
        _openssl("ecparam", "-name", "prime256v1", "-genkey", "-noout", "-out", f"{name}.key",
                 cwd=d)
    key("ca")
    _openssl("req", "-x509", "-new", "-key", "ca.key", "-days", "2", "-subj", "/CN=vasl test CA",
             "-out", "ca.crt", cwd=d)
    for name, ext in (("server", "subjectAltName=IP:127.0.0.1,DNS:localhost"),
                      ("client", "extendedKeyUsage=clientAuth")):
        key(name)
        _openssl("req", "-new", "-key", f"{name}.key", "-subj", f"/CN=vasl {name}",
                 "-out", f"{name}.csr", cwd=d)
        with open(os.path.join(d, f"{name}.ext"), "w") as f:
            f.write(ext + "\n")
        _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.crt", "-CAkey", "ca.key",
                 "-CAcreateserial", "-days", "2", "-extfile", f"{name}.ext",
                 "-out", f"{name}.crt", cwd=d)
    return {n: os.path.join(d, n) for n in ("ca.crt", "server.crt", "server.key", "client.crt",
                                            "client.key")}


class Vasld:
    def __init__(self, base: str, *extra: str, credentials=None):
        self.data_dir = os.path.join(base, "data")
        port_file = os.path.join(base, "port")
        self.log_path = os.path.join(base, "vasld.log")
        token_file = os.path.join(base, "admin.token")
        with open(token_file, "w") as f:
            f.write(ADMIN_TOKEN + "\n")
        self._log = open(self.log_path, "w")
        self.proc = subprocess.Popen(
            [_require(VASLD), "--address", "127.0.0.1:0", "--data-dir", self.data_dir,
             "--port-file", port_file, "--admin-token-file", token_file, *extra],
            stdout=self._log, stderr=subprocess.STDOUT)
        self.address = _port_file_address(port_file, self.proc, self.log_path)
        assert self.proc.poll() is None, self.log()
        self.credentials = credentials

    def channel(self, token: str | None = None, credentials="default"):
        creds = self.credentials if credentials == "default" else credentials
        ch = (grpc.secure_channel(self.address, creds) if creds is not None
              else grpc.insecure_channel(self.address))
        return ch

    def log(self) -> str:
        with open(self.log_path, errors="replace") as f:
            return f.read()

    def stop(self):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            self.proc.wait(timeout=60)
        self._log.close()


def _matrix_requests():
    """(method, kind, request factory, role needed); every request fails after authorisation
    (bad argument, unknown name, empty project) so that the matrix changes nothing."""
    from vasl._proto import vasl_pb2 as pb

    def ingest():
        yield pb.IngestScanRequest(header=pb.ScanHeader(project=PROJECT, scan=""))

    def backproject():
        yield pb.BackProjectRequest(header=pb.BackProjectHeader(project=PROJECT))

    p = PROJECT
    return [
        ("CreateProject", "uu", lambda: pb.CreateProjectRequest(name="Not A Name!"), "write*"),
        ("GetProject", "uu", lambda: pb.GetProjectRequest(project=p), "read"),
        ("ListProjects", "uu", lambda: pb.ListProjectsRequest(), "any"),
        ("ListScans", "uu", lambda: pb.ListScansRequest(project=p), "read"),
        ("IngestScan", "su", ingest, "write"),
        ("GetIngestProgress", "uu", lambda: pb.GetIngestProgressRequest(project=p), "read"),
        ("Render", "us", lambda: pb.RenderRequest(project=p, width_px=0, height_px=0), "read"),
        ("InspectRecords", "uu", lambda: pb.InspectRecordsRequest(project=p, version=-1), "read"),
        ("Rebuild", "uu", lambda: pb.RebuildRequest(project=p), "write"),
        ("DeleteScan", "uu", lambda: pb.DeleteScanRequest(project=p, scan="nope"), "admin"),
        ("ListVersions", "uu", lambda: pb.ListVersionsRequest(project=p), "read"),
        ("Export", "us", lambda: pb.ExportRequest(project=p, version=-1), "read"),
        ("CreateProfile", "uu", lambda: pb.CreateProfileRequest(project=p), "write"),
        ("GetProfile", "uu", lambda: pb.GetProfileRequest(project=p, name="nope"), "read"),
        ("ListProfiles", "uu", lambda: pb.ListProfilesRequest(project=p), "read"),
        ("SetActiveProfile", "uu", lambda: pb.SetActiveProfileRequest(project=p), "write"),
        ("Reweight", "uu", lambda: pb.ReweightRequest(project=p, revision=-1), "write"),
        ("QueryRecords", "uu", lambda: pb.QueryRecordsRequest(project=p), "read"),
        ("Normalise", "uu", lambda: pb.NormaliseRequest(project=p, base_profile="nope"), "write"),
        ("EstimateLens", "uu", lambda: pb.EstimateLensRequest(project=p, rig=""), "write"),
        ("ListLensMaps", "uu", lambda: pb.ListLensMapsRequest(project=p), "read"),
        ("PinVersion", "uu", lambda: pb.PinVersionRequest(project=p, version=999), "admin"),
        ("Rollback", "uu", lambda: pb.RollbackRequest(project=p, version=999), "admin"),
        ("BackProject", "su", backproject, "write"),
        ("CreateToken", "uu", lambda: pb.CreateTokenRequest(project=p), "admin"),
        ("ListTokens", "uu", lambda: pb.ListTokensRequest(project=p), "admin"),
        ("RevokeToken", "uu", lambda: pb.RevokeTokenRequest(id="000000000000"), "any"),
    ]


def _code(stub, method, kind, make, token):
    metadata = [("authorization", f"Bearer {token}")] if token else None
    call = getattr(stub, method)
    try:
        if kind == "us":
            for _ in call(make(), metadata=metadata, timeout=30):
                pass
        else:
            call(make(), metadata=metadata, timeout=30)
        return grpc.StatusCode.OK
    except grpc.RpcError as e:
        return e.code()


RANK = {"none": 0, "read": 1, "write": 2, "admin": 3}


def _allowed(need: str, caller: dict) -> bool:
    if caller["server_admin"]:
        return True
    if not caller["valid"]:
        return False
    if need == "any":
        return True
    if need == "write*":
        return caller["project"] == "*" and RANK[caller["role"]] >= RANK["write"]
    on_project = caller["project"] in (PROJECT, "*")
    return on_project and RANK[caller["role"]] >= RANK[need]


def _run_matrix(server: Vasld, label: str):
    from vasl import Client
    from vasl._proto import vasl_pb2_grpc as pb_grpc

    with Client(server.address, token=ADMIN_TOKEN, **server.client_tls) as admin:
        if PROJECT not in [p.name for p in admin.list_projects()]:
            admin.create_project(PROJECT, vossel_size_m=0.1)
            admin.create_project(OTHER, vossel_size_m=0.1)
        made = {name: admin.create_token(project, role, f"{label} {name}")
                for name, project, role in (("read", PROJECT, "read"),
                                            ("write", PROJECT, "write"),
                                            ("admin", PROJECT, "admin"),
                                            ("other-admin", OTHER, "admin"),
                                            ("all-write", "*", "write"),
                                            ("revoked", PROJECT, "admin"))}
        admin.revoke_token(made["revoked"]["id"])
    callers = {"no token": dict(token=None, valid=False, server_admin=False),
               "garbage": dict(token="vasl_000000000000_" + "0" * 64, valid=False,
                               server_admin=False),
               "server admin": dict(token=ADMIN_TOKEN, valid=True, server_admin=True)}
    for name, t in made.items():
        callers[name] = dict(token=t["token"], valid=name != "revoked", server_admin=False,
                             project=t["project"], role=t["role"])
    requests = _matrix_requests()
    wrong = []
    counts = {"denied": 0, "allowed": 0}
    with server.channel() as channel:
        stub = pb_grpc.VaslServiceStub(channel)
        for method, kind, make, need in requests:
            for cname, caller in callers.items():
                code = _code(stub, method, kind, make, caller["token"])
                allowed = _allowed(need, caller)
                if allowed:
                    ok = code not in DENIED
                elif not caller["valid"]:
                    ok = code == grpc.StatusCode.UNAUTHENTICATED
                else:
                    ok = code == grpc.StatusCode.PERMISSION_DENIED
                counts["allowed" if allowed else "denied"] += 1
                if not ok:
                    wrong.append(f"{method} as {cname}: {code.name} (allowed={allowed})")
    print(f"\naccess matrix ({label}): {len(requests)} RPCs x {len(callers)} callers = "
          f"{len(requests) * len(callers)} calls, {counts['allowed']} allowed, "
          f"{counts['denied']} refused, {len(wrong)} wrong")
    assert not wrong, "\n".join(wrong)
    return made


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    s = Vasld(str(tmp_path_factory.mktemp("vasld-acl")))
    s.client_tls = {}
    yield s
    s.stop()


@pytest.fixture(scope="module")
def mtls(tmp_path_factory):
    certs = make_certs(str(tmp_path_factory.mktemp("certs")))
    read = lambda n: open(certs[n], "rb").read()  # noqa: E731
    creds = grpc.ssl_channel_credentials(read("ca.crt"), read("client.key"), read("client.crt"))
    s = Vasld(str(tmp_path_factory.mktemp("vasld-tls")), "--tls-cert", certs["server.crt"],
              "--tls-key", certs["server.key"], "--tls-client-ca", certs["ca.crt"],
              credentials=creds)
    s.certs = certs
    s.client_tls = dict(tls_ca=certs["ca.crt"], tls_cert=certs["client.crt"],
                        tls_key=certs["client.key"])
    yield s
    s.stop()


def test_every_rpc_under_every_role_plaintext(plain):
    made = _run_matrix(plain, "plaintext")
    # The store keeps hashes only: no token's text is in access.sqlite (or its WAL).
    blob = b""
    for name in os.listdir(plain.data_dir):
        if name.startswith("access.sqlite"):
            with open(os.path.join(plain.data_dir, name), "rb") as f:
                blob += f.read()
    assert blob, "no token store in the data directory"
    for t in made.values():
        assert t["token"].encode() not in blob and t["token"].split("_")[-1].encode() not in blob


def test_every_rpc_under_every_role_mutual_tls(mtls):
    _run_matrix(mtls, "mutual TLS")


def test_tls_refuses_plaintext_and_clients_without_a_certificate(mtls):
    from vasl import Client, VaslError

    with Client(mtls.address, token=ADMIN_TOKEN, timeout_s=5) as c:  # plaintext to a TLS port
        with pytest.raises(VaslError) as e:
            c.list_projects()
        assert e.value.code == grpc.StatusCode.UNAVAILABLE
    with Client(mtls.address, token=ADMIN_TOKEN, timeout_s=5, tls_ca=mtls.certs["ca.crt"]) as c:
        with pytest.raises(VaslError) as e:  # TLS, but no client certificate
            c.list_projects()
        assert e.value.code == grpc.StatusCode.UNAUTHENTICATED
        assert "client certificate" in e.value.details
        print(f"\nmutual TLS, no client certificate: {e.value.details}")
        assert c.health() == "SERVING"  # health stays open for probes
    with Client(mtls.address, token=ADMIN_TOKEN, timeout_s=5, **mtls.client_tls) as c:
        assert PROJECT in [p.name for p in c.list_projects()]
        assert c.health() == "SERVING"
    assert "tls=mutual" in mtls.log() and "access_control=on" in mtls.log()


def test_health_probe_needs_no_client_certificate_under_mutual_tls(mtls, tmp_path):
    # The deploy probe beside a server certificate with no client key: SERVING.
    import shutil
    import subprocess
    import sys

    for name in ("ca.crt", "server.crt"):
        shutil.copy(mtls.certs[name], tmp_path / name)
    conf = tmp_path / "vasld.conf"
    conf.write_text(f"address = {mtls.address}\ntls-cert = {tmp_path / 'server.crt'}\n"
                    f"tls-client-ca = {tmp_path / 'ca.crt'}\n")
    probe = os.path.join(os.path.dirname(__file__), "..", "..", "deploy", "healthcheck.py")
    r = subprocess.run([sys.executable, probe, "--config", str(conf)], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "SERVING" in r.stdout


def test_health_is_open_and_tokens_are_scoped(plain, tmp_path):
    from grpc_health.v1 import health_pb2, health_pb2_grpc
    from vasl import Client, VaslError

    with plain.channel() as ch:  # no token
        r = health_pb2_grpc.HealthStub(ch).Check(health_pb2.HealthCheckRequest(), timeout=5)
        assert r.status == health_pb2.HealthCheckResponse.SERVING
    with Client(plain.address, token=ADMIN_TOKEN) as admin:
        if PROJECT not in [p.name for p in admin.list_projects()]:
            admin.create_project(PROJECT, vossel_size_m=0.1)
            admin.create_project(OTHER, vossel_size_m=0.1)
        reader = admin.create_token(OTHER, "read", "scoped")
        site_admin = admin.create_token(PROJECT, "admin", "scoped")
    with Client(plain.address, token=reader["token"]) as c:
        assert [p.name for p in c.list_projects()] == [OTHER]  # sees only what it may read
        with pytest.raises(VaslError) as e:
            c.get_project(PROJECT)
        assert e.value.code == grpc.StatusCode.PERMISSION_DENIED
        print(f"\nread token on {OTHER} asking for {PROJECT}: {e.value.details}")
        assert "read role on project 'acl'" in e.value.details
    with Client(plain.address, token=site_admin["token"]) as c:
        deputy = c.create_token(PROJECT, "write", "deputy")  # a project admin delegates
        assert deputy["created_by"] == site_admin["id"]
        assert {t["project"] for t in c.list_tokens()} == {PROJECT}
        for project, role in ((OTHER, "read"), ("*", "read")):
            with pytest.raises(VaslError) as e:
                c.create_token(project, role)
            assert e.value.code == grpc.StatusCode.PERMISSION_DENIED
        c.revoke_token(deputy["id"])
    with Client(plain.address, token=deputy["token"]) as c:
        with pytest.raises(VaslError) as e:
            c.get_project(PROJECT)
        assert e.value.code == grpc.StatusCode.UNAUTHENTICATED and "revoked" in e.value.details
    # The CLI reads its token from a file and says what to do without one.
    from conftest import run_cli

    class _S:
        address = plain.address
    token_file = tmp_path / "t"
    token_file.write_text(site_admin["token"] + "\n")
    r = run_cli(_S, "--token-file", str(token_file), "token", "list", "--project", PROJECT)
    assert site_admin["id"] in r.stdout
    r = run_cli(_S, "project", "list", check=False)
    assert r.returncode == 1 and "UNAUTHENTICATED" in r.stderr and "token" in r.stderr


def test_open_access_on_a_public_address_is_refused(tmp_path):
    r = subprocess.run([_require(VASLD), "--address", "0.0.0.0:0", "--data-dir",
                        str(tmp_path / "d")], capture_output=True, text=True, timeout=30)
    print(f"\n{r.stderr.strip()}")
    assert r.returncode == 2 and "--admin-token-file" in r.stderr


def test_reflection_describes_health_too(plain):
    pb2 = __import__("grpc_reflection.v1alpha.reflection_pb2", fromlist=["x"])
    pb2_grpc = __import__("grpc_reflection.v1alpha.reflection_pb2_grpc", fromlist=["x"])
    from google.protobuf import descriptor_pb2

    with plain.channel() as ch:
        stub = pb2_grpc.ServerReflectionStub(ch)
        reqs = [pb2.ServerReflectionRequest(file_containing_symbol=s)
                for s in ("grpc.health.v1.Health", "vasl.v1.VaslService")]
        out = list(stub.ServerReflectionInfo(iter(reqs), timeout=10))
    for r, package in zip(out, ("grpc.health.v1", "vasl.v1")):
        files = r.file_descriptor_response.file_descriptor_proto
        assert files, f"reflection gave no descriptor for {package}: {r}"
        packages = [descriptor_pb2.FileDescriptorProto.FromString(f).package for f in files]
        assert package in packages, packages
