#include "stage/processing/photometric_stage.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

namespace stage::processing {
namespace {

using ::testing::HasSubstr;

TEST(GeometrySpecTest, TheFlagNamesMvsNoneOrADirectoryAndMvsIsTheDefault) {
  EXPECT_EQ(GeometrySpec{}.source, GeometrySource::kMvs);
  EXPECT_EQ(PhotometricJob{}.geometry.source, GeometrySource::kMvs);
  EXPECT_EQ(GeometrySpec::Parse("mvs").source, GeometrySource::kMvs);
  EXPECT_EQ(GeometrySpec::Parse("none").source, GeometrySource::kNone);
  const GeometrySpec dir = GeometrySpec::Parse("ground_truth");
  EXPECT_EQ(dir.source, GeometrySource::kDirectory);
  EXPECT_EQ(dir.dir, "ground_truth");
  for (const std::string flag : {"mvs", "none", "ground_truth", "/abs/meshes"}) {
    EXPECT_EQ(GeometrySpec::Parse(flag).ToString(), flag);
    EXPECT_TRUE(GeometrySpec::Parse(flag).Validate().ok()) << flag;
  }
  EXPECT_FALSE(GeometrySpec::Parse("none").has_mesh());
  EXPECT_TRUE(GeometrySpec::Parse("mvs").has_mesh());
}

TEST(GeometrySpecTest, ADirectoryWithoutAPathOrAPathWithoutADirectoryIsRefused) {
  const absl::Status no_path = GeometrySpec{GeometrySource::kDirectory, ""}.Validate();
  EXPECT_EQ(no_path.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(no_path.message()), HasSubstr("needs its path"));
  const absl::Status stray = GeometrySpec{GeometrySource::kNone, "meshes"}.Validate();
  EXPECT_EQ(stray.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(stray.message()), HasSubstr("\"meshes\""));
  PhotometricJob job;
  job.take_dir = "/nonexistent-take";
  job.geometry = {GeometrySource::kMvs, "meshes"};
  EXPECT_EQ(RunPhotometric(job).status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(PathInTakeTest, RelativePathsAreUnderTheTakeAbsoluteOnesAreThemselves) {
  EXPECT_EQ(PathInTake("/t", "derived/x"), "/t/derived/x");
  EXPECT_EQ(PathInTake("/t", "/elsewhere/x", "derived/y"), "/elsewhere/x");
  EXPECT_EQ(PathInTake("/t", "", "derived/y"), "/t/derived/y");
  EXPECT_EQ(PathInTake("/t", ""), "");
}

}  // namespace
}  // namespace stage::processing
