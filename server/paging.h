/// @file paging.h
/// @brief Pages of the List RPCs: at most page_size items after the page token.
/// @details A token names the key of the last item a page returned ("after:<key>"), so a
///          page stays right when items are added or removed between calls (a version pruned
///          by retention, a scan added). Lists must be in ascending key order.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"

namespace vasl::server {

inline constexpr int32_t kDefaultPageSize = 100;
inline constexpr int32_t kMaxPageSize = 1000;

/// A key that orders like the integer `v` (non-negative ids and versions).
inline std::string IntKey(int64_t v) { return absl::StrFormat("%020d", v); }

/// The items of `all` (ascending by `key`) on the page that `page_token` starts, and the token
/// of the next page ("" when it is the last). INVALID_ARGUMENT for a negative page size or a
/// token this server did not write.
template <typename T, typename KeyFn>
absl::StatusOr<std::vector<const T*>> Page(const std::vector<T>& all, int32_t page_size,
                                           const std::string& page_token, KeyFn key,
                                           std::string* next_page_token) {
  if (page_size < 0) {
    return absl::InvalidArgumentError(absl::StrCat("page_size must be >= 0, got ", page_size));
  }
  const size_t size = size_t(page_size == 0 ? kDefaultPageSize : std::min(page_size, kMaxPageSize));
  constexpr char kPrefix[] = "after:";
  size_t first = 0;
  if (!page_token.empty()) {
    if (page_token.rfind(kPrefix, 0) != 0) {
      return absl::InvalidArgumentError("page_token is not one a List call returned");
    }
    const std::string after = page_token.substr(sizeof(kPrefix) - 1);
    while (first < all.size() && !(key(all[first]) > after)) ++first;
  }
  std::vector<const T*> out;
  for (size_t i = first; i < all.size() && out.size() < size; ++i) out.push_back(&all[i]);
  next_page_token->clear();
  if (first + out.size() < all.size() && !out.empty()) {
    *next_page_token = absl::StrCat(kPrefix, key(*out.back()));
  }
  return out;
}

}  // namespace vasl::server
