// AssignOnHugePages: the values it promises, storage reused when it suffices, and a large
// buffer's mapping advised for transparent huge pages before its first touch.
#include "lattice/memory/huge_pages.h"

#include <gtest/gtest.h>

#include <cstdint>
#include <fstream>
#include <sstream>
#include <string>

namespace vasl::memory {
namespace {

// The kernel's THP mode: the bracketed word of /sys/kernel/mm/transparent_hugepage/enabled
// ("always", "madvise", "never"), empty when the kernel has no THP.
std::string ThpMode() {
  std::ifstream in("/sys/kernel/mm/transparent_hugepage/enabled");
  std::string line;
  std::getline(in, line);
  const size_t a = line.find('['), b = line.find(']');
  return a == std::string::npos || b == std::string::npos ? "" : line.substr(a + 1, b - a - 1);
}

// The "THPeligible:" value of the mapping of /proc/self/smaps that holds `p`; -1 when none says.
int ThpEligible(const void* p) {
  std::ifstream in("/proc/self/smaps");
  std::string line;
  bool inside = false;
  const uintptr_t at = reinterpret_cast<uintptr_t>(p);
  while (std::getline(in, line)) {
    unsigned long long lo = 0, hi = 0;
    char dash = 0;
    std::istringstream head(line);
    if (head >> std::hex >> lo >> dash >> hi && dash == '-') {
      inside = at >= lo && at < hi;
      continue;
    }
    if (inside && line.rfind("THPeligible:", 0) == 0) return std::stoi(line.substr(12));
  }
  return -1;
}

TEST(HugePagesTest, AssignGivesNCopiesWhateverTheSize) {
  std::vector<float> small, large;
  AssignOnHugePages(small, 1000, 2.5f);
  ASSERT_EQ(small.size(), 1000u);
  for (float v : small) EXPECT_EQ(v, 2.5f);
  const size_t n = 3 * kHugePageMinBytes / sizeof(float) + 7;  // not a whole number of pages
  AssignOnHugePages(large, n, -1.0f);
  ASSERT_EQ(large.size(), n);
  EXPECT_EQ(large.front(), -1.0f);
  EXPECT_EQ(large[n / 2], -1.0f);
  EXPECT_EQ(large.back(), -1.0f);
}

TEST(HugePagesTest, StorageThatSufficesIsKept) {
  std::vector<double> v;
  const size_t n = 2 * kHugePageMinBytes / sizeof(double);
  AssignOnHugePages(v, n, 1.0);
  const double* first = v.data();
  AssignOnHugePages(v, n / 2, 3.0);  // fits: assign in place, no new allocation
  EXPECT_EQ(v.data(), first);
  ASSERT_EQ(v.size(), n / 2);
  EXPECT_EQ(v.back(), 3.0);
}

TEST(HugePagesTest, LargeBufferIsAdvisedBeforeItsFirstTouch) {
  const std::string mode = ThpMode();
  if (mode != "madvise" && mode != "always") {
    GTEST_SKIP() << "transparent huge pages are '" << mode
                 << "' in this kernel: no advice to observe";
  }
  std::vector<uint8_t> v;
  AssignOnHugePages(v, size_t(64) << 20, uint8_t{1});
  const int eligible = ThpEligible(v.data() + v.size() / 2);
  if (eligible < 0) GTEST_SKIP() << "/proc/self/smaps has no THPeligible field in this kernel";
  // In madvise mode a mapping is eligible only when advised (glibc maps 64 MB on its own).
  EXPECT_EQ(eligible, 1);
}

}  // namespace
}  // namespace vasl::memory
