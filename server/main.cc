/// @file main.cc
/// @brief vasld: the VASL gRPC server. Parses flags, opens the Engine on the data directory,
///        serves vasl.v1.VaslService with health checking and reflection, and shuts down
///        gracefully on SIGINT/SIGTERM.
#include <pthread.h>
#include <signal.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <fstream>
#include <iterator>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include <grpcpp/ext/proto_server_reflection_plugin.h>
#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/security/server_credentials.h>
#include <grpcpp/server.h>
#include <grpcpp/server_builder.h>

#include "absl/strings/ascii.h"
#include "lattice/engine.h"
#include "server/access.h"
#include "server/server_options.h"
#include "server/status_util.h"
#include "server/vasl_service.h"
#include "server/worker_pool.h"

namespace {

/// ":PORT" means loopback; otherwise the address is used as given.
std::string NormalizeAddress(const std::string& address) {
  if (!address.empty() && address[0] == ':') return "127.0.0.1" + address;
  return address;
}

std::string HostOf(const std::string& address) {
  const size_t colon = address.rfind(':');
  return colon == std::string::npos ? address : address.substr(0, colon);
}

bool IsLoopback(const std::string& host) {
  return host == "localhost" || host.rfind("127.", 0) == 0 || host == "[::1]" || host == "::1" ||
         host == "unix" || host.rfind("unix:", 0) == 0;
}

/// The whole of a small file (a key, a certificate, a token); empty on failure.
bool ReadSmallFile(const std::filesystem::path& path, std::string* out) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return false;
  out->assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  return in.good() || in.eof();
}

std::shared_ptr<grpc::ServerCredentials> Credentials(const vasl::server::ServerOptions& o,
                                                     std::string* error) {
  if (o.tls_cert.empty()) return grpc::InsecureServerCredentials();
  grpc::SslServerCredentialsOptions::PemKeyCertPair pair;
  if (!ReadSmallFile(o.tls_cert, &pair.cert_chain) || pair.cert_chain.empty()) {
    *error = "cannot read --tls-cert " + o.tls_cert.string();
    return nullptr;
  }
  if (!ReadSmallFile(o.tls_key, &pair.private_key) || pair.private_key.empty()) {
    *error = "cannot read --tls-key " + o.tls_key.string();
    return nullptr;
  }
  grpc::SslServerCredentialsOptions ssl(GRPC_SSL_DONT_REQUEST_CLIENT_CERTIFICATE);
  ssl.pem_key_cert_pairs.push_back(std::move(pair));
  if (!o.tls_client_ca.empty()) {
    if (!ReadSmallFile(o.tls_client_ca, &ssl.pem_root_certs) || ssl.pem_root_certs.empty()) {
      *error = "cannot read --tls-client-ca " + o.tls_client_ca.string();
      return nullptr;
    }
    // A certificate a client presents must verify; one without may connect, so that health
    // probes stay open, and the service refuses its calls (require_client_certificate).
    ssl.client_certificate_request = GRPC_SSL_REQUEST_CLIENT_CERTIFICATE_AND_VERIFY;
  }
  return grpc::SslServerCredentials(ssl);
}

bool WritePortFile(const std::filesystem::path& path, int port) {
  const std::filesystem::path tmp = path.string() + ".tmp";
  {
    std::ofstream out(tmp, std::ios::trunc);
    if (!out) return false;
    out << port << "\n";
    if (!out.flush()) return false;
  }
  std::error_code ec;
  std::filesystem::rename(tmp, path, ec);
  return !ec;
}

}  // namespace

int main(int argc, char** argv) {
  using vasl::server::StderrLogSink;
  absl::StatusOr<vasl::server::ServerOptions> parsed =
      vasl::server::ParseServerOptions(std::vector<std::string>(argv + 1, argv + argc));
  if (!parsed.ok()) {
    if (parsed.status().code() == absl::StatusCode::kCancelled) {  // --help
      std::fputs(std::string(parsed.status().message()).c_str(), stdout);
      return 0;
    }
    std::fprintf(stderr, "vasld: %s\n", std::string(parsed.status().message()).c_str());
    return 2;
  }
  vasl::server::ServerOptions options = *parsed;
  {
    std::error_code ec;
    const std::filesystem::path absolute = std::filesystem::absolute(options.data_dir, ec);
    if (!ec) options.data_dir = absolute;  // so that every path the store reports is absolute
  }

  // Block the shutdown signals in every thread (threads inherit the mask); main waits for them.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGINT);
  sigaddset(&signals, SIGTERM);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);

  absl::StatusOr<std::unique_ptr<vasl::Engine>> engine =
      vasl::Engine::Open(options.data_dir, options.engine);
  if (!engine.ok()) {
    std::fprintf(stderr, "vasld: cannot open the data directory %s: %s\n",
                 options.data_dir.c_str(), std::string(engine.status().message()).c_str());
    return 1;
  }

  const std::string address = NormalizeAddress(options.address);
  std::unique_ptr<vasl::server::AccessControl> access;
  if (options.admin_token_file.empty()) {
    if (!IsLoopback(HostOf(address)) && !options.allow_open_access) {
      std::fprintf(stderr,
                   "vasld: refusing to listen on %s without access control: give "
                   "--admin-token-file (or --allow-open-access to let anyone in)\n",
                   address.c_str());
      return 2;
    }
    access = vasl::server::AccessControl::Open();
  } else {
    std::string text;
    if (!ReadSmallFile(options.admin_token_file, &text)) {
      std::fprintf(stderr, "vasld: cannot read --admin-token-file %s\n",
                   options.admin_token_file.c_str());
      return 2;
    }
    const std::string token(absl::StripAsciiWhitespace(text.substr(0, text.find('\n'))));
    auto opened = vasl::server::AccessControl::Open(token, options.data_dir / "access.sqlite");
    if (!opened.ok()) {
      std::fprintf(stderr, "vasld: --admin-token-file %s: %s\n", options.admin_token_file.c_str(),
                   std::string(opened.status().message()).c_str());
      return 2;
    }
    access = std::move(*opened);
  }
  std::string tls_error;
  std::shared_ptr<grpc::ServerCredentials> credentials = Credentials(options, &tls_error);
  if (!credentials) {
    std::fprintf(stderr, "vasld: %s\n", tls_error.c_str());
    return 2;
  }

  {
    // Clients never see the server's paths, nor the text of internal errors (status_util.h).
    std::error_code ec;
    std::vector<std::string> hidden = {options.data_dir.string()};
    const std::filesystem::path canonical = std::filesystem::weakly_canonical(options.data_dir, ec);
    if (!ec) hidden.push_back(canonical.string());
    vasl::server::RedactStatuses(std::move(hidden), StderrLogSink);
  }

  {
    // Export staging files of an earlier vasld that was killed mid-export (ExportStagingPath).
    std::error_code ec;
    for (const auto& entry : std::filesystem::directory_iterator(options.data_dir, ec)) {
      if (entry.path().filename().string().rfind(".tmp-export-", 0) == 0) {
        std::filesystem::remove(entry.path(), ec);
      }
    }
  }

  int workers = options.workers;
  if (workers <= 0) workers = std::max(2u, std::thread::hardware_concurrency());
  vasl::server::WorkerPool pool(workers, static_cast<size_t>(options.max_queued_calls));
  // Changes run on a pool of their own: a long ingest or rebuild never holds up a render.
  vasl::server::WorkerPool change_pool(static_cast<int>(options.change_workers),
                                       static_cast<size_t>(options.max_queued_calls));
  vasl::server::ServiceOptions service_options;
  service_options.change_pool = &change_pool;
  service_options.require_client_certificate = !options.tls_client_ca.empty();
  service_options.staging_dir = options.data_dir;
  service_options.min_free_disk_bytes = options.min_free_disk_bytes;
  service_options.render_chunk_bytes = options.render_chunk_bytes;
  service_options.access = access.get();
  service_options.max_calls_per_client = static_cast<int>(options.max_calls_per_client);
  service_options.max_inflight_ingest_bytes = options.max_inflight_ingest_bytes;
  vasl::server::VaslServiceImpl service(engine->get(), &pool, service_options);

  grpc::EnableDefaultHealthCheckService(true);
  if (options.reflection) grpc::reflection::InitProtoReflectionServerBuilderPlugin();
  grpc::ServerBuilder builder;
  int port = 0;
  builder.AddListeningPort(address, credentials, &port);
  // gRPC sets SO_REUSEPORT by default: a second vasld on a port one already serves would start
  // and the kernel would split connections between them. Off: the second one fails to bind.
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);
  builder.RegisterService(&service);
  builder.SetMaxReceiveMessageSize(static_cast<int>(options.max_message_bytes));
  builder.SetMaxSendMessageSize(static_cast<int>(options.max_message_bytes));
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  if (!server || port == 0) {
    std::fprintf(stderr, "vasld: cannot listen on %s (address in use or not local?)\n",
                 address.c_str());
    return 1;
  }
  const std::string bound = HostOf(address) + ":" + std::to_string(port);
  std::printf("vasld listening on %s\n", bound.c_str());
  std::fflush(stdout);
  StderrLogSink("listening on " + bound + " data_dir=" + options.data_dir.string() +
                " workers=" + std::to_string(workers) +
                " change_workers=" + std::to_string(options.change_workers) +
                " max_message_bytes=" + std::to_string(options.max_message_bytes) +
                " access_control=" + (access->enabled() ? "on" : "off") +
                " tls=" + (options.tls_cert.empty() ? "off"
                           : options.tls_client_ca.empty() ? "on" : "mutual"));
  if (!options.port_file.empty() && !WritePortFile(options.port_file, port)) {
    StderrLogSink("warning: cannot write --port-file " + options.port_file.string());
  }

  int signal_number = 0;
  sigwait(&signals, &signal_number);
  StderrLogSink(std::string("received ") + (signal_number == SIGINT ? "SIGINT" : "SIGTERM") +
                ", shutting down");
  if (grpc::HealthCheckServiceInterface* health = server->GetHealthCheckService()) {
    health->SetServingStatus(false);
  }
  // A second signal stops at once; so does the end of the grace period with calls still
  // running. Nothing is lost either way: a commit is atomic, and what was not committed is
  // collected when its project next opens.
  const double grace_s = options.shutdown_grace_s;
  std::thread([signals, grace_s] {
    struct timespec wait{static_cast<time_t>(grace_s) + 5, 0};
    const int again = sigtimedwait(&signals, nullptr, &wait);
    StderrLogSink(again > 0 ? "second signal: stopping now, running calls are abandoned"
                            : "grace period over with calls still running: stopping now");
    std::_Exit(again > 0 ? 130 : 1);
  }).detach();
  // Running RPCs get the grace period; the pool keeps running so that their reactors finish.
  server->Shutdown(std::chrono::system_clock::now() +
                   std::chrono::milliseconds(static_cast<int64_t>(1e3 * options.shutdown_grace_s)));
  server->Wait();
  change_pool.Stop();
  pool.Stop();
  if (!options.port_file.empty()) {
    std::error_code ec;
    std::filesystem::remove(options.port_file, ec);
  }
  StderrLogSink("stopped");
  return 0;
}
