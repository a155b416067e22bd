// CheckRequestStrings (server/request_check.h): every text field of a request, at any depth, is
// bounded and printable before a handler reads it, and a refusal names the field, not its bytes.
#include "server/request_check.h"

#include <gtest/gtest.h>

#include "vasl/v1/vasl.pb.h"

namespace vasl::server {
namespace {

namespace v1 = ::vasl::v1;

TEST(RequestCheckTest, AcceptsOrdinaryRequests) {
  v1::CreateProjectRequest create;
  create.set_name("site-7");
  create.set_description(std::string(kDescriptionBytes, 'd'));  // the ceiling itself
  EXPECT_TRUE(CheckRequestStrings(create).ok());
  v1::IngestScanRequest ingest;
  ingest.mutable_header()->set_project("site-7");
  ingest.mutable_header()->set_scan("station 12 (north) — ünïcode");
  EXPECT_TRUE(CheckRequestStrings(ingest).ok());
  EXPECT_TRUE(CheckRequestStrings(v1::ListProjectsRequest()).ok());
}

TEST(RequestCheckTest, RefusesLongOrControlTextAtAnyDepthWithoutEchoingIt) {
  v1::CreateProjectRequest create;
  create.set_name("site-7");
  create.set_description(std::string(kDescriptionBytes + 1, 'd'));
  absl::Status s = CheckRequestStrings(create);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("field description has 4097 bytes"), std::string::npos) << s;

  v1::DeleteScanRequest del;
  del.set_project("site-7");
  del.set_scan(std::string(kTextBytes + 1, 's'));
  s = CheckRequestStrings(del);
  EXPECT_NE(s.message().find("field scan has 1025 bytes"), std::string::npos) << s;
  EXPECT_EQ(s.message().find("sss"), std::string::npos) << "echoes the input: " << s;

  v1::IngestScanRequest ingest;  // a nested message inside a oneof
  ingest.mutable_header()->set_project("site-7");
  ingest.mutable_header()->set_scan("ok\x1b]0;owned\x07");
  s = CheckRequestStrings(ingest);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("field header.scan has a control character (byte 27)"),
            std::string::npos) << s;
  EXPECT_EQ(s.message().find("owned"), std::string::npos) << "echoes the input: " << s;

  v1::RevokeTokenRequest revoke;
  revoke.set_id(std::string("a\0b", 3));
  s = CheckRequestStrings(revoke);
  EXPECT_NE(s.message().find("(byte 0)"), std::string::npos) << s;
  v1::GetProjectRequest del_char;
  del_char.set_project("a\x7f");
  EXPECT_FALSE(CheckRequestStrings(del_char).ok());
}

}  // namespace
}  // namespace vasl::server
