/// @file server_options.cc
/// @brief Flag and config-file parsing for vasld.
#include "server/server_options.h"

#include <fstream>
#include <functional>
#include <map>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/strip.h"
#include "absl/strings/ascii.h"

namespace vasl::server {
namespace {

using Setter = std::function<absl::Status(ServerOptions&, const std::string&)>;

absl::Status BadValue(const std::string& name, const std::string& value, const char* want) {
  return absl::InvalidArgumentError(
      absl::StrCat("--", name, "=", value, ": expected ", want));
}

Setter Int64(int64_t ServerOptions::*field, const std::string& name, int64_t min) {
  return [field, name, min](ServerOptions& o, const std::string& v) -> absl::Status {
    int64_t x = 0;
    if (!absl::SimpleAtoi(v, &x) || x < min) return BadValue(name, v, "an integer >= 1");
    o.*field = x;
    return absl::OkStatus();
  };
}

Setter EngineInt64(int64_t EngineLimits::*field, const std::string& name) {
  return [field, name](ServerOptions& o, const std::string& v) -> absl::Status {
    int64_t x = 0;
    if (!absl::SimpleAtoi(v, &x) || x < 1) return BadValue(name, v, "an integer >= 1");
    o.engine.*field = x;
    return absl::OkStatus();
  };
}

Setter EngineInt(int EngineLimits::*field, const std::string& name) {
  return [field, name](ServerOptions& o, const std::string& v) -> absl::Status {
    int x = 0;
    if (!absl::SimpleAtoi(v, &x) || x < 1) return BadValue(name, v, "an integer >= 1");
    o.engine.*field = x;
    return absl::OkStatus();
  };
}

Setter Path(std::filesystem::path ServerOptions::*field) {
  return [field](ServerOptions& o, const std::string& v) -> absl::Status {
    o.*field = v;
    return absl::OkStatus();
  };
}

Setter Bool(bool ServerOptions::*field, const std::string& name) {
  return [field, name](ServerOptions& o, const std::string& v) -> absl::Status {
    const std::string x = absl::AsciiStrToLower(v);
    if (x == "true" || x == "1" || x == "on" || x == "yes") {
      o.*field = true;
    } else if (x == "false" || x == "0" || x == "off" || x == "no") {
      o.*field = false;
    } else {
      return BadValue(name, v, "true or false");
    }
    return absl::OkStatus();
  };
}

const std::map<std::string, std::pair<Setter, std::string>>& Flags() {
  static const auto* flags = new std::map<std::string, std::pair<Setter, std::string>>{
      {"address",
       {[](ServerOptions& o, const std::string& v) {
          if (v.empty()) return BadValue("address", v, "host:port");
          o.address = v;
          return absl::OkStatus();
        },
        "host:port to listen on; port 0 picks a free port (default 127.0.0.1:50051)"}},
      {"data-dir",
       {[](ServerOptions& o, const std::string& v) {
          if (v.empty()) return BadValue("data-dir", v, "a directory");
          o.data_dir = v;
          return absl::OkStatus();
        },
        "directory holding one folder per project (default ./vasl-data)"}},
      {"port-file",
       {[](ServerOptions& o, const std::string& v) {
          o.port_file = v;
          return absl::OkStatus();
        },
        "write the bound port to this file once listening (default: none)"}},
      {"workers",
       {[](ServerOptions& o, const std::string& v) {
          int x = 0;
          if (!absl::SimpleAtoi(v, &x) || x < 0) return BadValue("workers", v, "an integer >= 0");
          o.workers = x;
          return absl::OkStatus();
        },
        "threads running renders, queries and reads; 0 = hardware threads, at least 2 "
        "(default 0)"}},
      {"change-workers",
       {Int64(&ServerOptions::change_workers, "change-workers", 1),
        "threads running changes (ingest, rebuild, reweight, ...), apart from the reads "
        "(default 2)"}},
      {"shutdown-grace-s",
       {[](ServerOptions& o, const std::string& v) {
          double x = 0;
          if (!absl::SimpleAtod(v, &x) || !(x >= 0)) {
            return BadValue("shutdown-grace-s", v, "seconds >= 0");
          }
          o.shutdown_grace_s = x;
          return absl::OkStatus();
        },
        "on SIGINT/SIGTERM, seconds running RPCs get before cancellation (default 30)"}},
      {"max-message-bytes",
       {Int64(&ServerOptions::max_message_bytes, "max-message-bytes", 1),
        "largest gRPC message received or sent (default 8388608)"}},
      {"max-queued-calls",
       {Int64(&ServerOptions::max_queued_calls, "max-queued-calls", 1),
        "calls that may wait for a worker; more are refused (default 256)"}},
      {"max-calls-per-client",
       {Int64(&ServerOptions::max_calls_per_client, "max-calls-per-client", 1),
        "calls one client address may have running at once (default 64)"}},
      {"max-inflight-ingest-bytes",
       {Int64(&ServerOptions::max_inflight_ingest_bytes, "max-inflight-ingest-bytes", 1),
        "bytes of incoming scans all uploads may hold at once (default 4294967296)"}},
      {"min-free-disk-bytes",
       {Int64(&ServerOptions::min_free_disk_bytes, "min-free-disk-bytes", 0),
        "calls that write project data are refused while the data directory has fewer free "
        "bytes (default 1073741824; 0: no floor)"}},
      {"render-chunk-bytes",
       {Int64(&ServerOptions::render_chunk_bytes, "render-chunk-bytes", 1),
        "payload size of streamed render chunks (default 1048576)"}},
      {"max-points",
       {EngineInt64(&EngineLimits::max_points_per_scan, "max-points"),
        "LiDAR points per scan (default 50000000)"}},
      {"max-panoramas",
       {EngineInt64(&EngineLimits::max_panoramas_per_scan, "max-panoramas"),
        "panoramas per scan (default 16)"}},
      {"max-image-bytes",
       {EngineInt64(&EngineLimits::max_image_bytes, "max-image-bytes"),
        "encoded bytes of one panorama (default 536870912)"}},
      {"max-image-pixels",
       {EngineInt64(&EngineLimits::max_image_pixels, "max-image-pixels"),
        "decoded pixels of one panorama (default 134217728)"}},
      {"max-snapshot-bytes",
       {EngineInt64(&EngineLimits::max_snapshot_bytes, "max-snapshot-bytes"),
        "bytes of a version a render, records query, ingest or rebuild holds at once, estimated "
        "from its tiles; a larger version is read (a rebuild: made) tile group by tile group "
        "(default 4294967296)"}},
      {"max-revisit-image-bytes",
       {EngineInt64(&EngineLimits::max_revisit_image_bytes, "max-revisit-image-bytes"),
        "decoded images of older cameras and points of older LiDARs that ingests revisit, kept "
        "between ingests (0: none; default 268435456)"}},
      {"max-render-width",
       {EngineInt(&EngineLimits::max_render_width_px, "max-render-width"),
        "render width, pixels (default 16384)"}},
      {"admin-token-file",
       {Path(&ServerOptions::admin_token_file),
        "file with the admin bearer token; set: every VaslService RPC needs a token (default: "
        "none, access control off)"}},
      {"allow-open-access",
       {Bool(&ServerOptions::allow_open_access, "allow-open-access"),
        "allow a non-loopback address without --admin-token-file (default false)"}},
      {"tls-cert",
       {Path(&ServerOptions::tls_cert), "PEM certificate chain: TLS with --tls-key (default: none)"}},
      {"tls-key", {Path(&ServerOptions::tls_key), "PEM private key of --tls-cert"}},
      {"tls-client-ca",
       {Path(&ServerOptions::tls_client_ca),
        "PEM CA bundle: require client certificates it signed (mutual TLS; default: none)"}},
      {"reflection",
       {Bool(&ServerOptions::reflection, "reflection"),
        "serve gRPC server reflection (default true)"}},
      {"max-render-height",
       {EngineInt(&EngineLimits::max_render_height_px, "max-render-height"),
        "render height, pixels (default 8192)"}},
  };
  return *flags;
}

absl::Status Apply(ServerOptions& options, const std::string& name, const std::string& value);

absl::Status ReadConfig(ServerOptions& options, const std::string& path) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(absl::StrCat("--config ", path, ": cannot open the file"));
  std::string line;
  int line_no = 0;
  while (std::getline(in, line)) {
    ++line_no;
    const size_t hash = line.find('#');
    if (hash != std::string::npos) line.resize(hash);
    absl::string_view text = absl::StripAsciiWhitespace(line);
    if (text.empty()) continue;
    const size_t eq = text.find('=');
    if (eq == absl::string_view::npos) {
      return absl::InvalidArgumentError(
          absl::StrCat(path, ":", line_no, ": expected `name = value`, got `", text, "`"));
    }
    std::string name(absl::StripAsciiWhitespace(text.substr(0, eq)));
    std::string value(absl::StripAsciiWhitespace(text.substr(eq + 1)));
    if (name == "config") {
      return absl::InvalidArgumentError(absl::StrCat(path, ":", line_no, ": nested config"));
    }
    absl::Status s = Apply(options, name, value);
    if (!s.ok()) {
      return absl::InvalidArgumentError(absl::StrCat(path, ":", line_no, ": ", s.message()));
    }
  }
  return absl::OkStatus();
}

absl::Status Apply(ServerOptions& options, const std::string& name, const std::string& value) {
  if (name == "config") return ReadConfig(options, value);
  auto it = Flags().find(name);
  if (it == Flags().end()) {
    return absl::InvalidArgumentError(absl::StrCat("unknown flag --", name, "; see --help"));
  }
  return it->second.first(options, value);
}

}  // namespace

std::string Usage() {
  std::string text =
      "usage: vasld [--name=value ...]\n"
      "  --config PATH  read `name = value` lines (flag names without --)\n";
  for (const auto& [name, entry] : Flags()) {
    absl::StrAppend(&text, "  --", name, "  ", entry.second, "\n");
  }
  return text;
}

absl::StatusOr<ServerOptions> ParseServerOptions(const std::vector<std::string>& args) {
  ServerOptions options;
  for (size_t i = 0; i < args.size(); ++i) {
    const std::string& arg = args[i];
    if (arg == "--help" || arg == "-h") return absl::CancelledError(Usage());
    if (arg.rfind("--", 0) != 0) {
      return absl::InvalidArgumentError(
          absl::StrCat("unexpected argument `", arg, "`; see --help"));
    }
    std::string name = arg.substr(2);
    std::string value;
    const size_t eq = name.find('=');
    if (eq != std::string::npos) {
      value = name.substr(eq + 1);
      name.resize(eq);
    } else {
      if (i + 1 >= args.size()) {
        return absl::InvalidArgumentError(absl::StrCat("--", name, " needs a value"));
      }
      value = args[++i];
    }
    absl::Status s = Apply(options, name, value);
    if (!s.ok()) return s;
  }
  if (options.render_chunk_bytes + 4096 > options.max_message_bytes) {
    return absl::InvalidArgumentError(absl::StrCat(
        "--render-chunk-bytes=", options.render_chunk_bytes,
        " must be at least 4096 below --max-message-bytes=", options.max_message_bytes));
  }
  if (options.tls_cert.empty() != options.tls_key.empty()) {
    return absl::InvalidArgumentError("--tls-cert and --tls-key go together: give both or neither");
  }
  if (!options.tls_client_ca.empty() && options.tls_cert.empty()) {
    return absl::InvalidArgumentError("--tls-client-ca needs --tls-cert and --tls-key");
  }
  return options;
}

}  // namespace vasl::server
