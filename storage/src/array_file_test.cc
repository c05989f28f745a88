// Array files: rows written come back, in place only once closed, with clear errors.
#include "stage/storage/array_file.h"

#include <filesystem>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace stage::storage {
namespace {

using ::testing::HasSubstr;

TEST(ArrayFileTest, RowsAndAttributesComeBackAndTheFileAppearsOnlyWhenClosed) {
  const std::string path = ::testing::TempDir() + "/arrays.h5";
  std::filesystem::remove(path);
  auto writer = ArrayFileWriter::Create(path);
  ASSERT_TRUE(writer.ok()) << writer.status();
  ASSERT_TRUE((*writer)->AddArray("geometry", ArrayType::kFloat32, {2, 3}, /*deflate=*/4).ok());
  ASSERT_TRUE((*writer)->AddArray("frame", ArrayType::kInt64, {}).ok());
  EXPECT_FALSE((*writer)->AddArray("frame", ArrayType::kInt64, {}).ok());
  for (int64_t r = 0; r < 3; ++r) {
    float row[6];
    for (int i = 0; i < 6; ++i) row[i] = static_cast<float>(10 * r + i);
    ASSERT_TRUE((*writer)->Append("geometry", row).ok());
    const int64_t frame = 100 + r;
    ASSERT_TRUE((*writer)->Append("frame", &frame).ok());
  }
  EXPECT_THAT((*writer)->Append("nothing", nullptr).message(), HasSubstr("no array \"nothing\""));
  ASSERT_TRUE((*writer)->SetAttribute("format", "test-1").ok());
  EXPECT_FALSE(std::filesystem::exists(path));
  ASSERT_TRUE((*writer)->Close().ok());
  EXPECT_TRUE(std::filesystem::exists(path));
  EXPECT_FALSE(std::filesystem::exists(path + ".tmp"));

  auto reader = ArrayFileReader::Open(path);
  ASSERT_TRUE(reader.ok()) << reader.status();
  EXPECT_EQ(*(*reader)->Shape("geometry"), (std::vector<int64_t>{3, 2, 3}));
  auto geometry = (*reader)->ReadAll<float>("geometry");
  ASSERT_TRUE(geometry.ok());
  EXPECT_EQ((*geometry)[6 * 2 + 5], 25.f);
  float row[6];
  ASSERT_TRUE((*reader)->ReadRows("geometry", ArrayType::kFloat32, 1, 1, row).ok());
  EXPECT_EQ(row[0], 10.f);
  EXPECT_EQ(*(*reader)->ReadAll<int64_t>("frame"), (std::vector<int64_t>{100, 101, 102}));
  EXPECT_EQ(*(*reader)->Attribute("format"), "test-1");
  EXPECT_THAT((*reader)->ReadRows("frame", ArrayType::kInt64, 2, 2, row).message(), HasSubstr("which has 3"));
  EXPECT_THAT((*reader)->Shape("images").status().message(), HasSubstr("no array \"images\""));
  EXPECT_THAT((*reader)->Attribute("rig").status().message(), HasSubstr("no text attribute \"rig\""));
}

TEST(ArrayFileTest, AnAbandonedWriterLeavesNothingAndBadFilesAreNamed) {
  const std::string path = ::testing::TempDir() + "/abandoned.h5";
  std::filesystem::remove(path);
  {
    auto writer = ArrayFileWriter::Create(path);
    ASSERT_TRUE(writer.ok());
    ASSERT_TRUE((*writer)->AddArray("x", ArrayType::kUint8, {4}).ok());
  }
  EXPECT_FALSE(std::filesystem::exists(path));
  EXPECT_FALSE(std::filesystem::exists(path + ".tmp"));
  EXPECT_THAT(ArrayFileReader::Open(path).status().message(), HasSubstr("no such file"));
  const std::string text = ::testing::TempDir() + "/not-hdf5.h5";
  {
    FILE* f = std::fopen(text.c_str(), "w");
    std::fputs("hello", f);
    std::fclose(f);
  }
  auto bad = ArrayFileReader::Open(text);
  ASSERT_FALSE(bad.ok());
  EXPECT_THAT(bad.status().message(), HasSubstr("not-hdf5.h5: not an HDF5 file"));
}

}  // namespace
}  // namespace stage::storage
