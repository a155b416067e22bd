/// @file vasl_service_test.cc
/// @brief The service's handlers over an in-process channel (no network) on a real Engine in a
///        temporary data directory: exact status codes for good and bad requests, and bad
///        input leaves the project unchanged (ARCHITECTURE.md "Errors and limits").
#include "server/vasl_service.h"

#include <cstdio>
#include <filesystem>
#include <memory>
#include <random>
#include <string>

#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include "server/worker_pool.h"
#include "vasl/v1/vasl.grpc.pb.h"

namespace vasl::server {
namespace {

namespace fs = std::filesystem;

class VaslServiceTest : public ::testing::Test {
 protected:
  void SetUp() override {
    std::random_device rd;
    dir_ = fs::temp_directory_path() / ("vasl_service_test_" + std::to_string(rd()));
    auto engine = Engine::Open(dir_);
    ASSERT_TRUE(engine.ok()) << engine.status();
    engine_ = std::move(*engine);
    pool_ = std::make_unique<WorkerPool>(2);
    ServiceOptions options;
    options.log = [](const std::string& line) { std::printf("log: %s\n", line.c_str()); };
    service_ = std::make_unique<VaslServiceImpl>(engine_.get(), pool_.get(), options);
    grpc::ServerBuilder builder;
    builder.RegisterService(service_.get());
    server_ = builder.BuildAndStart();
    ASSERT_NE(server_, nullptr);
    stub_ = v1::VaslService::NewStub(server_->InProcessChannel(grpc::ChannelArguments()));
  }
  void TearDown() override {
    if (server_) server_->Shutdown();
    if (pool_) pool_->Stop();
    server_.reset();
    service_.reset();
    engine_.reset();
    std::error_code ec;
    fs::remove_all(dir_, ec);
  }

  grpc::Status Create(const std::string& name, double vossel_size_m, v1::Project* out) {
    grpc::ClientContext ctx;
    v1::CreateProjectRequest req;
    req.set_name(name);
    req.set_vossel_size_m(vossel_size_m);
    return stub_->CreateProject(&ctx, req, out);
  }

  grpc::Status Ingest(const std::vector<v1::IngestScanRequest>& stream) {
    grpc::ClientContext ctx;
    v1::IngestScanResponse response;
    auto writer = stub_->IngestScan(&ctx, &response);
    for (const auto& r : stream) {
      if (!writer->Write(r)) break;
    }
    writer->WritesDone();
    return writer->Finish();
  }

  fs::path dir_;
  std::unique_ptr<Engine> engine_;
  std::unique_ptr<WorkerPool> pool_;
  std::unique_ptr<VaslServiceImpl> service_;
  std::unique_ptr<grpc::Server> server_;
  std::unique_ptr<v1::VaslService::Stub> stub_;
};

TEST_F(VaslServiceTest, ProjectLifecycleStatusCodes) {
  v1::Project project;
  grpc::Status s = Create("site", 0.05, &project);
  ASSERT_TRUE(s.ok()) << s.error_message();
  EXPECT_EQ(project.name(), "site");
  EXPECT_DOUBLE_EQ(project.vossel_size_m(), 0.05);
  EXPECT_EQ(project.head_version(), 0);
  EXPECT_EQ(Create("site", 0.05, &project).error_code(), grpc::StatusCode::ALREADY_EXISTS);
  EXPECT_EQ(Create("Bad Name!", 0.05, &project).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(Create("other", -1.0, &project).error_code(), grpc::StatusCode::INVALID_ARGUMENT);

  grpc::ClientContext ctx;
  v1::GetProjectRequest get;
  get.set_project("nope");
  EXPECT_EQ(stub_->GetProject(&ctx, get, &project).error_code(), grpc::StatusCode::NOT_FOUND);

  grpc::ClientContext list_ctx;
  v1::ListProjectsResponse list;
  ASSERT_TRUE(stub_->ListProjects(&list_ctx, v1::ListProjectsRequest(), &list).ok());
  ASSERT_EQ(list.projects_size(), 1);
  EXPECT_EQ(list.projects(0).name(), "site");
  std::printf("projects listed: %d\n", list.projects_size());
}

TEST_F(VaslServiceTest, MalformedIngestIsInvalidArgumentAndChangesNothing) {
  v1::Project project;
  ASSERT_TRUE(Create("site", 0.05, &project).ok());
  v1::IngestScanRequest points;
  points.mutable_points()->set_data(std::string(32, '\0'));
  v1::IngestScanRequest header;
  v1::ScanHeader* h = header.mutable_header();
  h->set_project("site");
  h->set_scan("s1");
  h->mutable_pose()->mutable_quaternion_xyzw()->set_w(1.0);
  h->mutable_lidar()->set_divergence_rad(3e-4);
  h->mutable_lidar()->set_point_count(2);
  v1::IngestScanRequest odd;
  odd.mutable_points()->set_data(std::string(20, '\0'));

  const grpc::Status no_header = Ingest({points});
  const grpc::Status empty = Ingest({});
  const grpc::Status odd_chunk = Ingest({header, odd});
  EXPECT_EQ(no_header.error_code(), grpc::StatusCode::INVALID_ARGUMENT)
      << no_header.error_message();
  EXPECT_EQ(empty.error_code(), grpc::StatusCode::INVALID_ARGUMENT)
      << empty.error_message();
  EXPECT_EQ(odd_chunk.error_code(), grpc::StatusCode::INVALID_ARGUMENT)
      << odd_chunk.error_message();
  std::printf("no header: %s\nodd chunk: %s\n", no_header.error_message().c_str(),
              odd_chunk.error_message().c_str());

  v1::IngestScanRequest unknown = header;
  unknown.mutable_header()->set_project("nope");
  EXPECT_EQ(Ingest({unknown, points}).error_code(), grpc::StatusCode::NOT_FOUND);

  grpc::ClientContext ctx;
  v1::GetProjectRequest get;
  get.set_project("site");
  ASSERT_TRUE(stub_->GetProject(&ctx, get, &project).ok());
  EXPECT_EQ(project.head_version(), 0);
  EXPECT_EQ(project.scan_count(), 0);

  grpc::ClientContext pctx;
  v1::GetIngestProgressRequest preq;
  preq.set_project("site");
  v1::IngestProgress progress;
  ASSERT_TRUE(stub_->GetIngestProgress(&pctx, preq, &progress).ok());
  EXPECT_EQ(progress.state(), v1::IngestProgress::STATE_FAILED);
}

TEST_F(VaslServiceTest, RenderValidatesBeforeTheEngine) {
  v1::Project project;
  ASSERT_TRUE(Create("site", 0.05, &project).ok());
  auto render = [&](const v1::RenderRequest& req) {
    grpc::ClientContext ctx;
    auto reader = stub_->Render(&ctx, req);
    v1::RenderResponse msg;
    while (reader->Read(&msg)) {
    }
    return reader->Finish();
  };
  v1::RenderRequest req;
  req.set_project("site");
  req.set_width_px(64);
  req.set_height_px(32);
  EXPECT_EQ(render(req).error_code(), grpc::StatusCode::INVALID_ARGUMENT);  // no pose
  req.mutable_pose()->mutable_quaternion_xyzw()->set_w(1.0);
  req.set_width_px(1 << 20);
  EXPECT_EQ(render(req).error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
  req.set_width_px(64);
  req.add_formats(static_cast<v1::ImageFormat>(7));
  EXPECT_EQ(render(req).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  req.clear_formats();
  req.set_project("nope");
  EXPECT_EQ(render(req).error_code(), grpc::StatusCode::NOT_FOUND);
}

}  // namespace
}  // namespace vasl::server
