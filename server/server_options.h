/// @file server_options.h
/// @brief vasld configuration: listening address, data directory and every limit a client
///        controls (ARCHITECTURE.md, "Errors and limits"), from flags and/or a config file.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "lattice/engine.h"

namespace vasl::server {

struct ServerOptions {
  /// host:port to listen on; port 0 picks a free port. A leading ':' means 127.0.0.1.
  std::string address = "127.0.0.1:50051";
  /// Directory with one folder per project.
  std::filesystem::path data_dir = "vasl-data";
  /// If set, the bound port is written here (decimal, newline) once the server listens.
  std::filesystem::path port_file;
  /// Largest gRPC message accepted or sent, bytes (clients send 1 MiB chunks).
  int64_t max_message_bytes = 8ll << 20;
  /// Size of the RenderChunk payloads the server streams, bytes.
  int64_t render_chunk_bytes = 1ll << 20;
  /// Worker threads for renders, queries and other reads; 0: the number of hardware threads
  /// (at least 2).
  int workers = 0;
  /// Worker threads for changes (ingest, back-projection, rebuild, deletion, reweight,
  /// rollback, normalisation): changes of different projects run side by side up to this many;
  /// they never take a reader's thread.
  int64_t change_workers = 2;
  /// On SIGINT/SIGTERM, running RPCs get this long to finish before they are cancelled, s.
  double shutdown_grace_s = 30.0;
  /// Calls that may wait for a worker; more get RESOURCE_EXHAUSTED.
  int64_t max_queued_calls = 256;
  /// Calls one client address may have running at once.
  int64_t max_calls_per_client = 64;
  /// Bytes of incoming scans all upload streams may hold at once.
  int64_t max_inflight_ingest_bytes = 4ll << 30;
  /// Calls that write project data are refused while the data directory's file system has
  /// fewer free bytes than this; 0: no floor.
  int64_t min_free_disk_bytes = 1ll << 30;
  /// Limits enforced by the engine and, for stream sizes, by the ingest assembler.
  EngineLimits engine;

  // Access control and transport security (server/access.h).
  /// A file holding the admin bearer token (first line, at least 16 characters). Set: every
  /// RPC of VaslService wants a token; empty: access control is off.
  std::filesystem::path admin_token_file;
  /// Listening on a non-loopback address without access control is refused unless this is set.
  bool allow_open_access = false;
  /// PEM server certificate chain and private key: TLS when both are set.
  std::filesystem::path tls_cert;
  std::filesystem::path tls_key;
  /// PEM CA bundle: clients must present a certificate it signed (mutual TLS).
  std::filesystem::path tls_client_ca;
  /// Serve gRPC server reflection (grpcurl, grpc_cli).
  bool reflection = true;
};

/// Usage text listing every flag with its default.
std::string Usage();

/// Parses `--name=value` / `--name value` flags. `--config PATH` reads `name = value` lines
/// (same names, '#' comments) at that point, so later flags override the file.
/// INVALID_ARGUMENT for an unknown flag or a bad value; `--help` returns CANCELLED with Usage().
absl::StatusOr<ServerOptions> ParseServerOptions(const std::vector<std::string>& args);

}  // namespace vasl::server
