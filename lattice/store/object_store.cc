#include "lattice/store/object_store.h"

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <mutex>
#include <system_error>
#include <thread>
#include <vector>

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
    // Hashed in memory and written once to a staging file, its writeback started but not
    // waited for; Sync waits for it, then takes the file in under its name. Only an object
    // whose bytes are on the disk is ever renamed over a name: an older version may share it.
    absl::StatusOr<std::string> sha = internal::Sha256Hex(bytes);
    if (!sha.ok()) return sha.status();
    const fs::path staged = StagingPath();
    if (absl::Status s = internal::WriteFileStartWriteback(staged, bytes); !s.ok()) {
      ::unlink(staged.c_str());
      return s;
    }
    std::lock_guard<std::mutex> lock(mu_);
    pending_.push_back({staged, dir_ / *sha});
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

  absl::Status Sync() override {
    std::vector<Pending> pending;
    {
      std::lock_guard<std::mutex> lock(mu_);
      pending.swap(pending_);
    }
    // The staged files' fsyncs on a few threads of their own (they wait on the disk, not a
    // core): the filesystem commits concurrent ones together.
    std::vector<absl::Status> synced(pending.size());
    std::atomic<size_t> next{0};
    auto fsync_each = [&] {
      for (size_t i = next++; i < pending.size(); i = next++) {
        synced[i] = internal::FsyncPath(pending[i].staged);
      }
    };
    std::vector<std::thread> threads;
    for (size_t t = 1; t < std::min<size_t>(kSyncThreads, pending.size()); ++t) {
      threads.emplace_back(fsync_each);
    }
    fsync_each();
    for (std::thread& t : threads) t.join();
    absl::Status status;
    for (size_t i = 0; i < pending.size(); ++i) {
      if (status.ok() && !synced[i].ok()) status = synced[i];
      if (status.ok() && ::rename(pending[i].staged.c_str(), pending[i].path.c_str()) != 0) {
        status = internal::ErrnoError("cannot rename object into place at", pending[i].path,
                                      errno);
      }
      if (!status.ok()) ::unlink(pending[i].staged.c_str());  // this one and those after it
    }
    if (!status.ok()) return status;
    return internal::FsyncPath(dir_);
  }

  void Discard() override {
    std::vector<Pending> pending;
    {
      std::lock_guard<std::mutex> lock(mu_);
      pending.swap(pending_);
    }
    for (const Pending& p : pending) ::unlink(p.staged.c_str());
  }

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

  /// Staged files fsynced at once by Sync.
  static constexpr size_t kSyncThreads = 8;
  struct Pending {
    fs::path staged;  ///< written, its writeback started
    fs::path path;    ///< its name once synced
  };
  fs::path dir_;
  std::mutex mu_;
  std::vector<Pending> pending_;
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
