#include "lattice/store/object_store.h"

#include <fcntl.h>
#include <unistd.h>

#include <cerrno>
#include <system_error>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "lattice/store/fs_util.h"

namespace vasl::store {
namespace fs = std::filesystem;
namespace {

constexpr char kStagingPrefix[] = ".tmp-";

class LocalObjectStore final : public ObjectStore {
 public:
  explicit LocalObjectStore(fs::path dir) : dir_(std::move(dir)) {}

  absl::StatusOr<StoredObject> PutBytes(std::string_view bytes) override {
    // Hashed in memory and written once (fsynced), never read back.
    absl::StatusOr<std::string> sha = internal::Sha256Hex(bytes);
    if (!sha.ok()) return sha.status();
    const fs::path staged = StagingPath();
    if (absl::Status s = internal::WriteFileDurable(staged, bytes); !s.ok()) {
      ::unlink(staged.c_str());
      return s;
    }
    const fs::path path = dir_ / *sha;
    if (::rename(staged.c_str(), path.c_str()) != 0) {
      const int err = errno;
      ::unlink(staged.c_str());
      return internal::ErrnoError("cannot rename object into place at", path, err);
    }
    return StoredObject{*sha, int64_t(bytes.size())};
  }

  absl::StatusOr<fs::path> LocalPath(const std::string& sha) const override {
    if (!IsSha256Hex(sha)) {
      return absl::InvalidArgumentError(absl::StrCat("\"", sha, "\" is not an object name"));
    }
    const fs::path path = dir_ / sha;
    std::error_code ec;
    if (!fs::is_regular_file(path, ec)) {
      return absl::NotFoundError(absl::StrCat("object ", sha, " is missing from ", dir_.string()));
    }
    return path;
  }

  absl::StatusOr<std::string> ReadBytes(const std::string& sha) const override {
    absl::StatusOr<fs::path> path = LocalPath(sha);
    if (!path.ok()) return path.status();
    return internal::ReadWholeFile(*path);
  }

  absl::StatusOr<std::vector<std::string>> List() const override {
    std::vector<std::string> out;
    std::error_code ec;
    for (const fs::directory_entry& e : fs::directory_iterator(dir_, ec)) {
      const std::string name = e.path().filename().string();
      if (IsSha256Hex(name)) out.push_back(name);
    }
    if (ec) return internal::ErrnoError("cannot list", dir_, ec.value());
    return out;
  }

  absl::Status Remove(const std::string& sha) override {
    if (!IsSha256Hex(sha)) return absl::InvalidArgumentError("not an object name");
    const fs::path path = dir_ / sha;
    if (::unlink(path.c_str()) != 0 && errno != ENOENT) {
      return internal::ErrnoError("cannot remove", path, errno);
    }
    return absl::OkStatus();
  }

  absl::Status Sync() override { return internal::FsyncPath(dir_); }

  absl::Status CleanStaging() override {
    std::error_code ec;
    for (const fs::directory_entry& e : fs::directory_iterator(dir_, ec)) {
      if (absl::StartsWith(e.path().filename().string(), kStagingPrefix)) {
        fs::remove(e.path(), ec);
      }
    }
    return absl::OkStatus();
  }

 private:
  // A fresh staging file's path, beside the objects (same filesystem: taking it in is a rename).
  fs::path StagingPath() const {
    return dir_ / absl::StrCat(kStagingPrefix, internal::RandomHex(16));
  }

  fs::path dir_;
};

}  // namespace

bool IsSha256Hex(const std::string& s) {
  if (s.size() != 64) return false;
  for (char c : s) {
    if (!((c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'))) return false;
  }
  return true;
}

absl::StatusOr<std::unique_ptr<ObjectStore>> OpenLocalObjectStore(const fs::path& dir) {
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec) return internal::ErrnoError("cannot create", dir, ec.value());
  return std::unique_ptr<ObjectStore>(new LocalObjectStore(dir));
}

}  // namespace vasl::store
