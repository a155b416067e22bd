#include "lattice/store/fs_util.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <ctime>
#include <memory>
#include <random>

#include <openssl/evp.h>

#include "absl/strings/str_cat.h"

namespace vasl::store::internal {
namespace fs = std::filesystem;

absl::Status ErrnoError(std::string_view what, const fs::path& path, int err) {
  return absl::InternalError(
      absl::StrCat(std::string(what), " ", path.string(), ": ", std::strerror(err)));
}

absl::Status FsyncPath(const fs::path& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return ErrnoError("cannot open for fsync", path, errno);
  const int rc = ::fsync(fd);
  const int err = errno;
  ::close(fd);
  if (rc != 0) return ErrnoError("fsync failed on", path, err);
  return absl::OkStatus();
}

absl::Status FsyncDirectoryTree(const fs::path& dir) {
  std::error_code ec;
  for (const fs::directory_entry& e : fs::directory_iterator(dir, ec)) {
    if (e.is_regular_file()) {
      if (absl::Status s = FsyncPath(e.path()); !s.ok()) return s;
    }
  }
  if (ec) return ErrnoError("cannot list", dir, ec.value());
  return FsyncPath(dir);
}

namespace {

/// Writes `bytes` to `path` (created or truncated), then `finish(fd)` (its status, errno set on
/// failure) before closing it.
template <typename Finish>
absl::Status WriteFile(const fs::path& path, std::string_view bytes, const char* finishing,
                       Finish&& finish) {
  const int fd = ::open(path.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) return ErrnoError("cannot create", path, errno);
  size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t w = ::write(fd, bytes.data() + done, bytes.size() - done);
    if (w < 0) {
      if (errno == EINTR) continue;
      const int err = errno;
      ::close(fd);
      return ErrnoError("cannot write", path, err);
    }
    done += static_cast<size_t>(w);
  }
  if (finish(fd) != 0) {
    const int err = errno;
    ::close(fd);
    return ErrnoError(finishing, path, err);
  }
  if (::close(fd) != 0) return ErrnoError("cannot close", path, errno);
  return absl::OkStatus();
}

}  // namespace

absl::Status WriteFileDurable(const fs::path& path, std::string_view bytes) {
  return WriteFile(path, bytes, "fsync failed on", [](int fd) { return ::fsync(fd); });
}

absl::Status WriteFileStartWriteback(const fs::path& path, std::string_view bytes) {
  return WriteFile(path, bytes, "cannot start the writeback of", [](int fd) {
    return ::sync_file_range(fd, 0, 0, SYNC_FILE_RANGE_WRITE);
  });
}

absl::Status ReplaceFileAtomically(const fs::path& path, std::string_view bytes) {
  const fs::path tmp =
      path.parent_path() / absl::StrCat(".", path.filename().string(), ".tmp-", RandomHex(12));
  if (absl::Status s = WriteFileDurable(tmp, bytes); !s.ok()) {
    ::unlink(tmp.c_str());
    return s;
  }
  if (::rename(tmp.c_str(), path.c_str()) != 0) {
    const int err = errno;
    ::unlink(tmp.c_str());
    return ErrnoError("cannot rename onto", path, err);
  }
  return FsyncPath(path.parent_path());
}

absl::StatusOr<std::string> ReadWholeFile(const fs::path& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    if (errno == ENOENT) return absl::NotFoundError(absl::StrCat("no such file: ", path.string()));
    return ErrnoError("cannot open", path, errno);
  }
  struct stat st {};
  std::string out;
  if (::fstat(fd, &st) == 0 && st.st_size > 0) out.reserve(static_cast<size_t>(st.st_size));
  char buf[1 << 16];
  for (;;) {
    const ssize_t r = ::read(fd, buf, sizeof(buf));
    if (r < 0) {
      if (errno == EINTR) continue;
      const int err = errno;
      ::close(fd);
      return ErrnoError("cannot read", path, err);
    }
    if (r == 0) break;
    out.append(buf, static_cast<size_t>(r));
  }
  ::close(fd);
  return out;
}

absl::StatusOr<std::string> Sha256Hex(std::string_view bytes) {
  std::unique_ptr<EVP_MD_CTX, decltype(&EVP_MD_CTX_free)> ctx(EVP_MD_CTX_new(), EVP_MD_CTX_free);
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int len = 0;
  if (!ctx || EVP_DigestInit_ex(ctx.get(), EVP_sha256(), nullptr) != 1 ||
      EVP_DigestUpdate(ctx.get(), bytes.data(), bytes.size()) != 1 ||
      EVP_DigestFinal_ex(ctx.get(), digest, &len) != 1) {
    return absl::InternalError("OpenSSL EVP sha256 failed");
  }
  static constexpr char kHex[] = "0123456789abcdef";
  std::string hex(2 * len, '0');
  for (unsigned int i = 0; i < len; ++i) {
    hex[2 * i] = kHex[digest[i] >> 4];
    hex[2 * i + 1] = kHex[digest[i] & 15];
  }
  return hex;
}

std::string RandomHex(int chars) {
  static thread_local std::mt19937_64 rng(std::random_device{}());
  static constexpr char kHex[] = "0123456789abcdef";
  std::string s(static_cast<size_t>(chars), '0');
  for (char& c : s) c = kHex[rng() & 15];
  return s;
}

std::string UtcNowIso8601() {
  const std::time_t now = std::time(nullptr);
  std::tm tm{};
  ::gmtime_r(&now, &tm);
  char buf[32];
  std::strftime(buf, sizeof(buf), "%Y-%m-%dT%H:%M:%SZ", &tm);
  return buf;
}

}  // namespace vasl::store::internal
