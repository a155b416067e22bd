/// @file fs_util.h
/// @brief Durable file operations of the project store: fsync of files and directories,
///        write-temp-then-rename, sha256 (OpenSSL EVP), random names and UTC timestamps.
/// @details Errors are INTERNAL with the path and the errno text (ARCHITECTURE.md "Errors").
#pragma once

#include <filesystem>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"

namespace vasl::store::internal {

/// INTERNAL error "<what> <path>: <strerror(err)>".
absl::Status ErrnoError(std::string_view what, const std::filesystem::path& path, int err);
/// fsyncs a regular file or a directory (its entries: creations, renames, removals).
absl::Status FsyncPath(const std::filesystem::path& path);
/// fsyncs every regular file directly inside `dir`, then `dir` itself.
absl::Status FsyncDirectoryTree(const std::filesystem::path& dir);
/// Writes `bytes` to `path` (created or truncated) and fsyncs the file.
absl::Status WriteFileDurable(const std::filesystem::path& path, std::string_view bytes);
/// Writes `bytes` to `path` (created or truncated) and starts its writeback to the disk
/// (sync_file_range) without waiting for it: a later FsyncPath of it waits less.
absl::Status WriteFileStartWriteback(const std::filesystem::path& path, std::string_view bytes);
/// Replaces `path` atomically: writes `<dir>/.<name>.tmp-<random>`, fsyncs it, renames it over
/// `path` and fsyncs the directory. A crash leaves either the old or the new content.
absl::Status ReplaceFileAtomically(const std::filesystem::path& path, std::string_view bytes);
/// Reads a whole file. NOT_FOUND if it does not exist.
absl::StatusOr<std::string> ReadWholeFile(const std::filesystem::path& path);
/// Lowercase hex sha256 of `bytes`.
absl::StatusOr<std::string> Sha256Hex(std::string_view bytes);
/// `chars` random lowercase hex characters (std::random_device).
std::string RandomHex(int chars);
/// Current time, UTC, ISO 8601 with seconds: "2026-01-31T12:34:56Z".
std::string UtcNowIso8601();

}  // namespace vasl::store::internal
