#!/usr/bin/env python3
"""Health probe of a local vasld (container HEALTHCHECK, systemd or monitoring): asks the
unauthenticated gRPC health service (grpc.health.v1.Health/Check, service "") and exits 0 when
the server reports SERVING, 1 otherwise (NOT_SERVING while it shuts down, unreachable, TLS
failure), printing one line saying why.

It reads vasld's config file (`name = value` lines, `#` comments) for `address` (a wildcard host
becomes 127.0.0.1) and, when `tls-cert` is set, speaks TLS:
  - the server is verified against --ca (default $VASL_HEALTH_CA, else ca.crt beside the
    tls-cert file if there is one, else the tls-cert file itself: fine for a self-signed
    certificate or a file holding the chain up to its root);
  - the name checked is --server-name (default $VASL_HEALTH_SERVER_NAME, else localhost);
  - the health service needs no client certificate, also under mutual TLS; the probe presents
    --cert / --key (default $VASL_HEALTH_CERT / $VASL_HEALTH_KEY) when given, else client.crt /
    client.key beside the tls-cert file when both are there.
Needs only grpcio and grpcio-health-checking.
"""
from __future__ import annotations

import argparse
import os
import sys


def read_config(path: str) -> dict:
    out = {}
    if not path:
        return out
    with open(path) as f:
        for line in f:
            line = line.split("#", 1)[0].strip()
            if not line or "=" not in line:
                continue
            name, value = (s.strip() for s in line.split("=", 1))
            out[name.replace("_", "-")] = value
    return out


def local_target(address: str) -> str:
    host, _, port = address.rpartition(":")
    if host in ("", "0.0.0.0", "[::]", "::", "*"):
        host = "127.0.0.1"
    return f"{host}:{port}"


def read(path: str) -> bytes:
    with open(path, "rb") as f:
        return f.read()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=os.environ.get("VASL_CONFIG", "/etc/vasl/vasld.conf"),
                    help="vasld's config file (default $VASL_CONFIG or /etc/vasl/vasld.conf; "
                         "'' for none)")
    ap.add_argument("--address", help="host:port (default: the config's address, else "
                                      "127.0.0.1:50051)")
    ap.add_argument("--ca", default=os.environ.get("VASL_HEALTH_CA"))
    ap.add_argument("--cert", default=os.environ.get("VASL_HEALTH_CERT"))
    ap.add_argument("--key", default=os.environ.get("VASL_HEALTH_KEY"))
    ap.add_argument("--server-name", default=os.environ.get("VASL_HEALTH_SERVER_NAME", "localhost"))
    ap.add_argument("--plaintext", action="store_true", help="no TLS whatever the config says")
    ap.add_argument("--timeout", type=float, default=3.0, help="seconds (default 3)")
    args = ap.parse_args(argv)

    try:
        import grpc
        from grpc_health.v1 import health_pb2, health_pb2_grpc
    except ImportError as e:
        print(f"healthcheck: {e} (needs grpcio and grpcio-health-checking)")
        return 1
    try:
        conf = read_config(args.config) if args.config else {}
    except OSError as e:
        print(f"healthcheck: cannot read the config: {e}")
        return 1
    target = local_target(args.address or conf.get("address", "127.0.0.1:50051"))
    cert = conf.get("tls-cert", "")
    try:
        if cert and not args.plaintext:
            here = os.path.dirname(cert)
            ca = args.ca or next((p for p in (os.path.join(here, "ca.crt"), cert)
                                  if os.path.isfile(p)), cert)
            # Health answers without a client certificate, also under mutual TLS; one that is
            # named, or lies beside tls-cert, is presented (and must then verify).
            client_cert = client_key = None
            cert_path = args.cert or os.path.join(here, "client.crt")
            key_path = args.key or os.path.join(here, "client.key")
            if args.cert or args.key or (os.path.isfile(cert_path) and os.path.isfile(key_path)):
                client_cert, client_key = read(cert_path), read(key_path)
            creds = grpc.ssl_channel_credentials(read(ca), client_key, client_cert)
            channel = grpc.secure_channel(target, creds, options=[
                ("grpc.ssl_target_name_override", args.server_name)])
        else:
            channel = grpc.insecure_channel(target)
    except OSError as e:
        print(f"healthcheck: {e}")
        return 1
    with channel:
        try:
            r = health_pb2_grpc.HealthStub(channel).Check(
                health_pb2.HealthCheckRequest(service=""), timeout=args.timeout)
        except grpc.RpcError as e:
            print(f"healthcheck: {target}: {e.code().name}: {e.details()}")
            return 1
    status = health_pb2.HealthCheckResponse.ServingStatus.Name(r.status)
    print(f"healthcheck: {target}: {status}")
    return 0 if r.status == health_pb2.HealthCheckResponse.SERVING else 1


if __name__ == "__main__":
    sys.exit(main())
