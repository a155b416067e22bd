/// @file access.cc
/// @brief Bearer tokens with roles, hashed in SQLite (access.h).
#include "server/access.h"

#include <openssl/crypto.h>
#include <openssl/rand.h>
#include <openssl/sha.h>
#include <sqlite3.h>

#include <algorithm>
#include <ctime>

#include "absl/strings/ascii.h"
#include "absl/strings/strip.h"
#include "absl/strings/str_cat.h"
#include "lattice/ingest/validate.h"

namespace vasl::server {
namespace {

constexpr char kPrefix[] = "vasl_";
constexpr size_t kIdHex = 12;
constexpr size_t kSecretBytes = 32;
constexpr size_t kMaxLabel = 200;

std::string Hex(const unsigned char* bytes, size_t n) {
  static const char* digits = "0123456789abcdef";
  std::string out(2 * n, '0');
  for (size_t i = 0; i < n; ++i) {
    out[2 * i] = digits[bytes[i] >> 4];
    out[2 * i + 1] = digits[bytes[i] & 15];
  }
  return out;
}

std::string HashOf(const std::string& token) {
  unsigned char digest[SHA256_DIGEST_LENGTH];
  SHA256(reinterpret_cast<const unsigned char*>(token.data()), token.size(), digest);
  return Hex(digest, sizeof(digest));
}

absl::StatusOr<std::string> RandomHex(size_t bytes) {
  std::string raw(bytes, '\0');
  if (RAND_bytes(reinterpret_cast<unsigned char*>(raw.data()), static_cast<int>(bytes)) != 1) {
    return absl::InternalError("the system's random source failed");
  }
  return Hex(reinterpret_cast<const unsigned char*>(raw.data()), bytes);
}

std::string NowUtc() {
  const std::time_t now = std::time(nullptr);
  std::tm tm_utc{};
  gmtime_r(&now, &tm_utc);
  char stamp[32];
  std::strftime(stamp, sizeof(stamp), "%Y-%m-%dT%H:%M:%SZ", &tm_utc);
  return stamp;
}

bool IsHex(const std::string& s) {
  for (char c : s) {
    if (!((c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'))) return false;
  }
  return true;
}

/// One prepared statement, finalized on scope exit.
class Statement {
 public:
  Statement(sqlite3* db, const char* sql) { sqlite3_prepare_v2(db, sql, -1, &stmt_, nullptr); }
  ~Statement() { sqlite3_finalize(stmt_); }
  sqlite3_stmt* get() const { return stmt_; }
  void Bind(int i, const std::string& text) {
    sqlite3_bind_text(stmt_, i, text.data(), static_cast<int>(text.size()), SQLITE_TRANSIENT);
  }
  std::string Text(int i) const {
    const unsigned char* t = sqlite3_column_text(stmt_, i);
    return t ? reinterpret_cast<const char*>(t) : "";
  }

 private:
  sqlite3_stmt* stmt_ = nullptr;
};

// The catalog's errors stay in the server log; callers get a plain message without paths or SQL.
absl::Status StoreError(sqlite3* db, const char* what) {
  return absl::InternalError(absl::StrCat("the token store could not ", what, " (",
                                          sqlite3_errstr(sqlite3_errcode(db)), ")"));
}

}  // namespace

const char* RoleName(Role role) {
  switch (role) {
    case Role::kRead: return "read";
    case Role::kWrite: return "write";
    case Role::kAdmin: return "admin";
    default: return "none";
  }
}

Role Caller::RoleOn(const std::string& project) const {
  if (admin) return Role::kAdmin;
  if (!token || !token->revoked_utc.empty()) return Role::kNone;
  if (token->project == kAllProjects || token->project == project) return token->role;
  return Role::kNone;
}

std::string Caller::Name() const {
  if (admin) return "admin";
  if (token) return "token " + token->id;
  return "anonymous";
}

std::unique_ptr<AccessControl> AccessControl::Open() {
  return std::unique_ptr<AccessControl>(new AccessControl());
}

absl::StatusOr<std::unique_ptr<AccessControl>> AccessControl::Open(
    const std::string& admin_token, const std::filesystem::path& db_path) {
  if (admin_token.size() < 16) {
    return absl::InvalidArgumentError("the admin token must have at least 16 characters");
  }
  std::unique_ptr<AccessControl> access(new AccessControl());
  access->enabled_ = true;
  access->admin_hash_ = HashOf(admin_token);
  if (sqlite3_open_v2(db_path.c_str(), &access->db_,
                      SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE | SQLITE_OPEN_FULLMUTEX,
                      nullptr) != SQLITE_OK) {
    return absl::UnavailableError(
        "cannot open the token store access.sqlite in the data directory");
  }
  sqlite3_busy_timeout(access->db_, 5000);
  const char* schema =
      "PRAGMA journal_mode=WAL; PRAGMA synchronous=FULL;"
      "CREATE TABLE IF NOT EXISTS tokens("
      "  id TEXT PRIMARY KEY, hash TEXT NOT NULL UNIQUE, project TEXT NOT NULL,"
      "  role INTEGER NOT NULL, label TEXT NOT NULL, created_utc TEXT NOT NULL,"
      "  revoked_utc TEXT, created_by TEXT NOT NULL);";
  if (sqlite3_exec(access->db_, schema, nullptr, nullptr, nullptr) != SQLITE_OK) {
    return StoreError(access->db_, "create its table");
  }
  if (absl::Status s = access->Load(); !s.ok()) return s;
  return access;
}

AccessControl::~AccessControl() {
  if (db_) sqlite3_close(db_);
}

absl::Status AccessControl::Load() {
  Statement q(db_, "SELECT id, hash, project, role, label, created_utc, "
                   "COALESCE(revoked_utc, ''), created_by FROM tokens");
  int rc;
  while ((rc = sqlite3_step(q.get())) == SQLITE_ROW) {
    TokenInfo t;
    t.id = q.Text(0);
    t.project = q.Text(2);
    const int role = sqlite3_column_int(q.get(), 3);
    t.role = role >= 1 && role <= 3 ? static_cast<Role>(role) : Role::kNone;
    t.label = q.Text(4);
    t.created_utc = q.Text(5);
    t.revoked_utc = q.Text(6);
    t.created_by = q.Text(7);
    by_hash_[q.Text(1)] = std::move(t);
  }
  return rc == SQLITE_DONE ? absl::OkStatus() : StoreError(db_, "read its tokens");
}

absl::StatusOr<Caller> AccessControl::Authenticate(const std::string& authorization) const {
  Caller caller;
  if (!enabled_) {
    caller.authenticated = caller.admin = true;
    return caller;
  }
  if (authorization.empty()) {
    return absl::UnauthenticatedError(
        "this server requires a token: send `authorization: Bearer <token>` (the vasl client "
        "reads VASL_TOKEN or VASL_TOKEN_FILE)");
  }
  absl::string_view value = authorization;
  if (!absl::ConsumePrefix(&value, "Bearer ") && !absl::ConsumePrefix(&value, "bearer ")) {
    return absl::UnauthenticatedError("the authorization header must read `Bearer <token>`");
  }
  const std::string token(absl::StripAsciiWhitespace(value));
  const std::string hash = HashOf(token);
  if (CRYPTO_memcmp(hash.data(), admin_hash_.data(), hash.size()) == 0) {
    caller.authenticated = caller.admin = true;
    return caller;
  }
  std::lock_guard<std::mutex> lock(mutex_);
  auto it = by_hash_.find(hash);
  if (it == by_hash_.end()) return absl::UnauthenticatedError("the token is not valid");
  if (!it->second.revoked_utc.empty()) {
    return absl::UnauthenticatedError(
        absl::StrCat("token ", it->second.id, " was revoked at ", it->second.revoked_utc));
  }
  caller.authenticated = true;
  caller.token = it->second;
  return caller;
}

absl::Status AccessControl::Require(const Caller& caller, const std::string& project, Role need,
                                    const char* what) {
  if (caller.RoleOn(project) >= need) return absl::OkStatus();
  const std::string where =
      project == kAllProjects ? "every project" : absl::StrCat("project '", project, "'");
  return absl::PermissionDeniedError(absl::StrCat(
      what, " needs the ", RoleName(need), " role on ", where, "; ", caller.Name(), " has ",
      RoleName(caller.RoleOn(project))));
}

absl::StatusOr<std::pair<TokenInfo, std::string>> AccessControl::Create(
    const Caller& caller, const std::string& project, Role role, const std::string& label) {
  if (!enabled_) {
    return absl::FailedPreconditionError(
        "access control is off on this server: start vasld with --admin-token-file to use tokens");
  }
  if (project.empty()) {
    return absl::InvalidArgumentError("project is empty: name one, or '*' for every project");
  }
  if (absl::Status s = Require(caller, project, Role::kAdmin, "creating a token"); !s.ok()) {
    return s;
  }
  if (role != Role::kRead && role != Role::kWrite && role != Role::kAdmin) {
    return absl::InvalidArgumentError("role must be read, write or admin");
  }
  if (absl::Status s = ingest::ValidateText("the label", label, kMaxLabel, true); !s.ok()) {
    return s;
  }
  absl::StatusOr<std::string> id = RandomHex(kIdHex / 2);
  absl::StatusOr<std::string> secret = RandomHex(kSecretBytes);
  if (!id.ok()) return id.status();
  if (!secret.ok()) return secret.status();
  std::string token = absl::StrCat(kPrefix, *id, "_", *secret);
  TokenInfo info;
  info.id = *id;
  info.project = project;
  info.role = role;
  info.label = label;
  info.created_utc = NowUtc();
  info.created_by = caller.admin ? "admin" : caller.token->id;
  const std::string hash = HashOf(token);
  std::lock_guard<std::mutex> lock(mutex_);
  Statement ins(db_, "INSERT INTO tokens(id, hash, project, role, label, created_utc, created_by)"
                     " VALUES(?, ?, ?, ?, ?, ?, ?)");
  ins.Bind(1, info.id);
  ins.Bind(2, hash);
  ins.Bind(3, info.project);
  sqlite3_bind_int(ins.get(), 4, static_cast<int>(role));
  ins.Bind(5, info.label);
  ins.Bind(6, info.created_utc);
  ins.Bind(7, info.created_by);
  if (sqlite3_step(ins.get()) != SQLITE_DONE) return StoreError(db_, "save the new token");
  by_hash_[hash] = info;
  return std::make_pair(info, std::move(token));
}

absl::StatusOr<std::vector<TokenInfo>> AccessControl::List(const Caller& caller,
                                                           const std::string& project) const {
  if (!enabled_) return std::vector<TokenInfo>();
  if (!project.empty()) {
    if (absl::Status s = Require(caller, project, Role::kAdmin, "listing tokens"); !s.ok()) {
      return s;
    }
  }
  std::vector<TokenInfo> out;
  std::lock_guard<std::mutex> lock(mutex_);
  for (const auto& [hash, t] : by_hash_) {
    if (!project.empty() && t.project != project) continue;
    if (caller.RoleOn(t.project) < Role::kAdmin) continue;
    out.push_back(t);
  }
  std::sort(out.begin(), out.end(), [](const TokenInfo& a, const TokenInfo& b) {
    return a.created_utc != b.created_utc ? a.created_utc < b.created_utc : a.id < b.id;
  });
  return out;
}

absl::StatusOr<TokenInfo> AccessControl::Revoke(const Caller& caller, const std::string& id) {
  if (!enabled_) {
    return absl::FailedPreconditionError("access control is off on this server: no tokens");
  }
  if (id.size() != kIdHex || !IsHex(id)) {
    return absl::InvalidArgumentError(
        absl::StrCat("a token id is ", kIdHex, " lowercase hex digits (see `vasl token list`)"));
  }
  std::lock_guard<std::mutex> lock(mutex_);
  for (auto& [hash, t] : by_hash_) {
    if (t.id != id) continue;
    // Unknown and not-yours look the same to a caller who may not see the token.
    if (caller.RoleOn(t.project) < Role::kAdmin) break;
    if (!t.revoked_utc.empty()) return t;
    const std::string when = NowUtc();
    Statement up(db_, "UPDATE tokens SET revoked_utc = ? WHERE id = ?");
    up.Bind(1, when);
    up.Bind(2, id);
    if (sqlite3_step(up.get()) != SQLITE_DONE) return StoreError(db_, "revoke the token");
    t.revoked_utc = when;
    return t;
  }
  return absl::NotFoundError(absl::StrCat("no token ", id, " that you administer"));
}

}  // namespace vasl::server
