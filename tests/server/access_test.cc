/// @file access_test.cc
/// @brief Access control (server/access.h): roles nest and stay within their project, tokens
///        survive a restart, only their hash is stored, revocation is immediate, and no caller
///        grants more than it holds.
#include "server/access.h"

#include <fstream>
#include <iterator>

#include <gtest/gtest.h>

namespace vasl::server {
namespace {

constexpr char kAdminToken[] = "admin-secret-0123456789";

class AccessTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = std::filesystem::temp_directory_path() /
           ("vasl-access-" + std::to_string(::testing::UnitTest::GetInstance()->random_seed()) +
            "-" + ::testing::UnitTest::GetInstance()->current_test_info()->name());
    std::filesystem::remove_all(dir_);
    std::filesystem::create_directories(dir_);
    access_ = Open();
  }
  void TearDown() override { std::filesystem::remove_all(dir_); }

  std::unique_ptr<AccessControl> Open() {
    auto opened = AccessControl::Open(kAdminToken, dir_ / "access.sqlite");
    EXPECT_TRUE(opened.ok()) << opened.status();
    return opened.ok() ? std::move(*opened) : nullptr;
  }
  Caller Admin() { return *access_->Authenticate(std::string("Bearer ") + kAdminToken); }
  /// A token made by the admin, and its caller.
  std::pair<std::string, Caller> Make(const std::string& project, Role role) {
    auto made = access_->Create(Admin(), project, role, "test");
    EXPECT_TRUE(made.ok()) << made.status();
    auto caller = access_->Authenticate("Bearer " + made->second);
    EXPECT_TRUE(caller.ok()) << caller.status();
    return {made->second, *caller};
  }

  std::filesystem::path dir_;
  std::unique_ptr<AccessControl> access_;
};

TEST_F(AccessTest, NoTokenOrABadOneIsUnauthenticated) {
  for (const std::string header : {"", "Bearer ", "Bearer nope", "Basic abc", kAdminToken}) {
    auto caller = access_->Authenticate(header);
    ASSERT_FALSE(caller.ok()) << "'" << header << "' was accepted";
    EXPECT_EQ(caller.status().code(), absl::StatusCode::kUnauthenticated) << caller.status();
  }
  EXPECT_TRUE(Admin().admin);
}

TEST_F(AccessTest, RolesNestAndStayOnTheirProject) {
  const Caller reader = Make("site", Role::kRead).second;
  const Caller writer = Make("site", Role::kWrite).second;
  const Caller everywhere = Make(kAllProjects, Role::kWrite).second;
  EXPECT_TRUE(AccessControl::Require(reader, "site", Role::kRead, "x").ok());
  EXPECT_EQ(AccessControl::Require(reader, "site", Role::kWrite, "ingesting").code(),
            absl::StatusCode::kPermissionDenied);
  EXPECT_TRUE(AccessControl::Require(writer, "site", Role::kRead, "x").ok());
  EXPECT_TRUE(AccessControl::Require(writer, "site", Role::kWrite, "x").ok());
  EXPECT_FALSE(AccessControl::Require(writer, "site", Role::kAdmin, "x").ok());
  EXPECT_FALSE(AccessControl::Require(writer, "other", Role::kRead, "x").ok());
  EXPECT_FALSE(AccessControl::Require(writer, kAllProjects, Role::kWrite, "x").ok());
  EXPECT_TRUE(AccessControl::Require(everywhere, "other", Role::kWrite, "x").ok());
  EXPECT_TRUE(AccessControl::Require(everywhere, kAllProjects, Role::kWrite, "x").ok());
  const absl::Status denied = AccessControl::Require(reader, "site", Role::kWrite, "ingesting");
  std::printf("denied: %s\n", std::string(denied.message()).c_str());
  EXPECT_NE(denied.message().find("write role on project 'site'"), std::string::npos) << denied;
}

TEST_F(AccessTest, NoCallerGrantsMoreThanItHolds) {
  const Caller site_admin = Make("site", Role::kAdmin).second;
  const Caller writer = Make("site", Role::kWrite).second;
  EXPECT_TRUE(access_->Create(site_admin, "site", Role::kAdmin, "deputy").ok());
  EXPECT_EQ(access_->Create(site_admin, "other", Role::kRead, "").status().code(),
            absl::StatusCode::kPermissionDenied);
  EXPECT_EQ(access_->Create(site_admin, kAllProjects, Role::kRead, "").status().code(),
            absl::StatusCode::kPermissionDenied);
  EXPECT_EQ(access_->Create(writer, "site", Role::kRead, "").status().code(),
            absl::StatusCode::kPermissionDenied);
  EXPECT_EQ(access_->Create(Admin(), "site", Role::kNone, "").status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(access_->Create(Admin(), "site", Role::kRead, "line\nbreak").status().code(),
            absl::StatusCode::kInvalidArgument);
  // A project admin lists its project's tokens only.
  Make("other", Role::kRead);
  auto listed = access_->List(site_admin, "");
  ASSERT_TRUE(listed.ok());
  for (const TokenInfo& t : *listed) EXPECT_EQ(t.project, "site");
  EXPECT_EQ(listed->size(), 3u);  // site admin, writer, deputy, and none of "other"
  EXPECT_EQ(access_->List(*access_->Authenticate("Bearer " + Make("site", Role::kRead).first),
                          "site").status().code(),
            absl::StatusCode::kPermissionDenied);
}

TEST_F(AccessTest, RevocationIsImmediateAndTokensSurviveARestartAsHashesOnly) {
  const auto [kept, kept_caller] = Make("site", Role::kWrite);
  const auto [gone, gone_caller] = Make("site", Role::kRead);
  auto revoked = access_->Revoke(Admin(), gone_caller.token->id);
  ASSERT_TRUE(revoked.ok()) << revoked.status();
  EXPECT_FALSE(revoked->revoked_utc.empty());
  EXPECT_EQ(access_->Authenticate("Bearer " + gone).status().code(),
            absl::StatusCode::kUnauthenticated);
  EXPECT_EQ(access_->Revoke(kept_caller, "0123456789ab").status().code(),
            absl::StatusCode::kNotFound);
  EXPECT_EQ(access_->Revoke(Admin(), "../etc").status().code(), absl::StatusCode::kInvalidArgument);

  access_.reset();
  std::ifstream in(dir_ / "access.sqlite", std::ios::binary);
  const std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  std::string wal;
  if (std::filesystem::exists(dir_ / "access.sqlite-wal")) {
    std::ifstream w(dir_ / "access.sqlite-wal", std::ios::binary);
    wal.assign(std::istreambuf_iterator<char>(w), std::istreambuf_iterator<char>());
  }
  const std::string secret = kept.substr(kept.rfind('_') + 1);
  EXPECT_EQ(bytes.find(secret), std::string::npos) << "a token's secret is stored in clear";
  EXPECT_EQ(wal.find(secret), std::string::npos) << "a token's secret is in the WAL in clear";

  access_ = Open();
  auto again = access_->Authenticate("Bearer " + kept);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_EQ(again->RoleOn("site"), Role::kWrite);
  EXPECT_EQ(access_->Authenticate("Bearer " + gone).status().code(),
            absl::StatusCode::kUnauthenticated);
}

TEST(AccessOffTest, EveryCallerIsAdminAndTokensAreRefused) {
  std::unique_ptr<AccessControl> access = AccessControl::Open();
  auto caller = access->Authenticate("");
  ASSERT_TRUE(caller.ok());
  EXPECT_EQ(caller->RoleOn("anything"), Role::kAdmin);
  EXPECT_EQ(access->Create(*caller, "site", Role::kRead, "").status().code(),
            absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(AccessControl::Open("short", "/tmp/x.sqlite").status().code(),
            absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace vasl::server
