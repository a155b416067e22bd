// The local object store of tile files (object_store.h): a put is named, readable and durable
// once the next Sync returns; puts no Sync took in are discarded without a trace.
#include "lattice/store/object_store.h"

#include <unistd.h>

#include <filesystem>
#include <string>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

namespace vasl::store {
namespace {

namespace fs = std::filesystem;

fs::path TestDir(const std::string& name) {
  fs::path dir = fs::temp_directory_path() /
                 ("vasl-objects-" + name + "-" + std::to_string(::getpid()));
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

/// Every file of `dir`, objects and staging files alike.
std::vector<std::string> FilesIn(const fs::path& dir) {
  std::vector<std::string> out;
  for (const fs::directory_entry& e : fs::directory_iterator(dir)) {
    out.push_back(e.path().filename().string());
  }
  return out;
}

TEST(ObjectStoreTest, APutIsNamedWhenTheSyncReturns) {
  const fs::path dir = TestDir("sync");
  auto objects = OpenLocalObjectStore(dir);
  ASSERT_TRUE(objects.ok()) << objects.status();
  const std::string bytes(1 << 20, 'a');
  auto put = (*objects)->PutBytes(bytes);
  ASSERT_TRUE(put.ok()) << put.status();
  EXPECT_EQ(put->bytes, int64_t(bytes.size()));
  // Not under its name before the sync: nothing may name an object not yet on the disk.
  EXPECT_EQ((*objects)->LocalPath(put->sha256).status().code(), absl::StatusCode::kNotFound);
  auto listed = (*objects)->List();
  ASSERT_TRUE(listed.ok());
  EXPECT_TRUE(listed->empty());

  ASSERT_TRUE((*objects)->Sync().ok());
  auto read = (*objects)->ReadBytes(put->sha256);
  ASSERT_TRUE(read.ok()) << read.status();
  EXPECT_EQ(*read, bytes);
  EXPECT_EQ(FilesIn(dir), std::vector<std::string>{put->sha256});  // no staging file left
  fs::remove_all(dir);
}

TEST(ObjectStoreTest, DiscardLeavesNoTraceAndKeepsSyncedObjects) {
  const fs::path dir = TestDir("discard");
  auto objects = OpenLocalObjectStore(dir);
  ASSERT_TRUE(objects.ok()) << objects.status();
  auto kept = (*objects)->PutBytes("kept");
  ASSERT_TRUE(kept.ok());
  ASSERT_TRUE((*objects)->Sync().ok());

  auto dropped = (*objects)->PutBytes("dropped");
  auto again = (*objects)->PutBytes("kept");  // a re-put of an object an older version has
  ASSERT_TRUE(dropped.ok() && again.ok());
  EXPECT_EQ(again->sha256, kept->sha256);
  EXPECT_EQ(FilesIn(dir).size(), 3u);  // the object and two staging files
  (*objects)->Discard();
  EXPECT_EQ(FilesIn(dir), std::vector<std::string>{kept->sha256});
  auto read = (*objects)->ReadBytes(kept->sha256);
  ASSERT_TRUE(read.ok());
  EXPECT_EQ(*read, "kept");
  // A sync after the discard names nothing of what was discarded.
  ASSERT_TRUE((*objects)->Sync().ok());
  EXPECT_EQ((*objects)->LocalPath(dropped->sha256).status().code(), absl::StatusCode::kNotFound);
  fs::remove_all(dir);
}

TEST(ObjectStoreTest, PutsFromManyThreadsAreAllNamedByOneSync) {
  const fs::path dir = TestDir("threads");
  auto objects = OpenLocalObjectStore(dir);
  ASSERT_TRUE(objects.ok()) << objects.status();
  constexpr int kThreads = 4, kEach = 25;
  std::vector<std::vector<std::string>> names(kThreads);
  std::vector<std::thread> threads;
  for (int t = 0; t < kThreads; ++t) {
    threads.emplace_back([&, t] {
      for (int i = 0; i < kEach; ++i) {
        // Same bytes from every thread for i < 5: one name put several times.
        const std::string bytes = i < 5 ? "shared " + std::to_string(i)
                                        : "object " + std::to_string(t) + "/" + std::to_string(i);
        auto put = (*objects)->PutBytes(bytes);
        if (put.ok()) names[t].push_back(put->sha256);
      }
    });
  }
  for (std::thread& t : threads) t.join();
  ASSERT_TRUE((*objects)->Sync().ok());
  for (int t = 0; t < kThreads; ++t) {
    ASSERT_EQ(names[t].size(), size_t(kEach));
    for (int i = 0; i < kEach; ++i) {
      auto read = (*objects)->ReadBytes(names[t][i]);
      ASSERT_TRUE(read.ok()) << read.status();
      EXPECT_EQ(*read, i < 5 ? "shared " + std::to_string(i)
                             : "object " + std::to_string(t) + "/" + std::to_string(i));
    }
  }
  // 5 shared objects and kThreads · 20 of their own, no staging file.
  EXPECT_EQ(FilesIn(dir).size(), size_t(5 + kThreads * (kEach - 5)));
  fs::remove_all(dir);
}

}  // namespace
}  // namespace vasl::store
