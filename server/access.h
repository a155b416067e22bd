/// @file access.h
/// @brief Access control of vasld (issue "Reliability and security"): bearer tokens with a role
///        per project, kept hashed in the data directory's access.sqlite, and the admin token
///        named by the server's config.
/// @details A token reads `vasl_<id>_<secret>`: `id` (12 hex digits) names it in lists and
///          revocations, `secret` is 32 random bytes in hex. Only SHA-256(token) is stored, so a
///          copy of the data directory grants nothing. A token holds one role on one project, or
///          on every project (`*`). Roles nest: admin ⊃ write ⊃ read.
///          - read: everything that does not change a project (get, list, render, inspect,
///            query, export, progress, versions, profiles);
///          - write: adds data and derives from it (ingest, back-projection, profiles, reweight,
///            normalise, rebuild); on `*` also creates projects;
///          - admin: takes things away or governs (delete a scan, roll back, pin versions) and
///            manages the project's tokens.
///          Without an admin token in the config, access control is off: every caller is admin
///          (vasld refuses that on a non-loopback address unless told --allow-open-access).
/// @warning Thread-safe. Tokens are cached in memory; creation and revocation write through to
///          SQLite before they take effect.
#pragma once

#include <filesystem>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

struct sqlite3;

namespace vasl::server {

enum class Role { kNone = 0, kRead = 1, kWrite = 2, kAdmin = 3 };

/// "read", "write", "admin" (or "none").
const char* RoleName(Role role);

/// The project a token covers when it covers every project.
inline constexpr char kAllProjects[] = "*";

struct TokenInfo {
  std::string id;            ///< 12 hex digits, public
  std::string project;       ///< a project name, or kAllProjects
  Role role = Role::kNone;
  std::string label;         ///< free text from its creator (who holds it, what for)
  std::string created_utc;   ///< RFC 3339
  std::string revoked_utc;   ///< empty while valid
  std::string created_by;    ///< id of the token that created it ("admin": the config's token)
};

/// Who is calling: the token presented (after validation).
struct Caller {
  bool authenticated = false;  ///< a valid token was presented (or access control is off)
  bool admin = false;          ///< the config's admin token (or access control is off)
  std::optional<TokenInfo> token;
  /// The caller's role on `project` (kNone when none).
  Role RoleOn(const std::string& project) const;
  /// "admin", "token <id>" or "anonymous", for logs.
  std::string Name() const;
};

class AccessControl {
 public:
  /// Access control off: every caller is admin.
  static std::unique_ptr<AccessControl> Open();
  /// Access control on: `admin_token` (at least 16 characters) is the admin's; tokens live in
  /// `db_path` (created if missing, WAL).
  static absl::StatusOr<std::unique_ptr<AccessControl>> Open(const std::string& admin_token,
                                                             const std::filesystem::path& db_path);
  ~AccessControl();
  AccessControl(const AccessControl&) = delete;
  AccessControl& operator=(const AccessControl&) = delete;

  bool enabled() const { return enabled_; }

  /// Validates the value of an `authorization` header ("Bearer <token>", or empty when the
  /// call carried none). UNAUTHENTICATED when access control is on and the token is missing,
  /// malformed, unknown or revoked.
  absl::StatusOr<Caller> Authenticate(const std::string& authorization) const;

  /// OK when `caller` holds at least `need` on `project`; PERMISSION_DENIED naming the role and
  /// project otherwise. `project` kAllProjects asks for a role on every project.
  static absl::Status Require(const Caller& caller, const std::string& project, Role need,
                              const char* what);

  /// A new token for `project` with `role`; `caller` must be admin of `project` (of every
  /// project for kAllProjects) and cannot grant more than it holds. Returns the info and the
  /// token's full text, which is shown only once.
  absl::StatusOr<std::pair<TokenInfo, std::string>> Create(const Caller& caller,
                                                           const std::string& project, Role role,
                                                           const std::string& label);
  /// The tokens `caller` administers: of `project`, or (empty) of every project it is admin of.
  /// Revoked tokens are listed with their revocation time.
  absl::StatusOr<std::vector<TokenInfo>> List(const Caller& caller,
                                              const std::string& project) const;
  /// Revokes token `id`; `caller` must be admin of its project. NOT_FOUND for an unknown id.
  absl::StatusOr<TokenInfo> Revoke(const Caller& caller, const std::string& id);

 private:
  AccessControl() = default;
  absl::Status Load();

  bool enabled_ = false;
  std::string admin_hash_;  // hex SHA-256 of the admin token
  sqlite3* db_ = nullptr;
  mutable std::mutex mutex_;
  std::map<std::string, TokenInfo> by_hash_;  // hex SHA-256 of the token -> info
};

}  // namespace vasl::server
