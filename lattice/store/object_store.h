/// @file object_store.h
/// @brief Content-addressed objects (tile files, reach rasters): the one small storage
///        interface through which tile and manifest objects are written and read, so that a
///        store spanning machines can put them in an object store (ARCHITECTURE.md "Beyond one
///        machine"). The embedded default is a local directory, `objects/<sha256>`.
/// @warning Implementations are thread-safe: any number of concurrent Put and read calls.
#pragma once

#include <cstdint>
#include <filesystem>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"

namespace vasl::store {

/// What Put stored.
struct StoredObject {
  std::string sha256;  ///< lowercase hex: the object's name
  int64_t bytes = 0;   ///< its size
};

class ObjectStore {
 public:
  virtual ~ObjectStore() = default;
  /// Stores bytes as an object named by their content hash. It is readable, and durable,
  /// once the next Sync returns: a writer puts many objects, then syncs once before anything
  /// names them, so that no put waits on the disk. Idempotent. (Tile files are made in memory:
  /// records::EncodeGeometry and its siblings.)
  virtual absl::StatusOr<StoredObject> PutBytes(std::string_view bytes) = 0;
  /// A local file holding the object, to read it in place (OpenVDB opens files).
  /// NOT_FOUND when there is no such object.
  virtual absl::StatusOr<std::filesystem::path> LocalPath(const std::string& sha256) const = 0;
  virtual absl::StatusOr<std::string> ReadBytes(const std::string& sha256) const = 0;
  /// Names of every stored object.
  virtual absl::StatusOr<std::vector<std::string>> List() const = 0;
  /// Removes an object (no error when it is already gone).
  virtual absl::Status Remove(const std::string& sha256) = 0;
  /// Makes every object put so far durable under its name, and the set of names durable.
  virtual absl::Status Sync() = 0;
  /// Forgets the objects put since the last Sync (a writer that stopped before naming them),
  /// removing what they left. Call under the one writer, as the garbage collection runs.
  virtual void Discard() = 0;
  /// Removes staging files left by an interrupted writer.
  virtual absl::Status CleanStaging() = 0;
};

/// Objects as files `dir/<sha256>`; staging files `dir/.tmp-*` beside them (same filesystem,
/// so taking a file in is a rename).
absl::StatusOr<std::unique_ptr<ObjectStore>> OpenLocalObjectStore(const std::filesystem::path& dir);

/// True for 64 lowercase hex characters.
bool IsSha256Hex(const std::string& s);

}  // namespace vasl::store
