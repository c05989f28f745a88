// Calibration files: a round trip keeps every number; a broken file is refused naming the file and the field; a model
// resized to the images keeps its projection (pixel corners scale).
#include "stage/common/camera_calibration.h"

#include <Eigen/Geometry>
#include <filesystem>
#include <unistd.h>

#include <fstream>

#include "gtest/gtest.h"
#include "stage/common/file_util.h"

namespace stage {
namespace {

CameraModel Model() {
  CameraParameters p;
  p.width = 2592;
  p.height = 2048;
  p.fx = 7301.5;
  p.fy = 7299.25;
  p.cx = 1297.3;
  p.cy = 1021.9;
  p.distortion = {-0.05, 0.1, 3e-4, -2e-4, 0.01};
  p.position = {10.5, -3.25, 1000.125};
  p.rotation = Eigen::AngleAxisd(0.3, Eigen::Vector3d(0.2, 1, 0.1).normalized()).toRotationMatrix();
  auto m = CameraModel::FromParameters(p);
  EXPECT_TRUE(m.ok()) << m.status();
  return *m;
}

std::string TempPath(const std::string& name) {
  return (std::filesystem::temp_directory_path() / (name + std::to_string(::getpid()) + ".json")).string();
}

TEST(CameraCalibrationTest, ARoundTripKeepsEveryNumber) {
  CameraCalibration cal;
  cal.source = "test";
  cal.cameras.push_back({"mv-01", Model()});
  const std::string path = TempPath("calibration");
  ASSERT_TRUE(WriteCameraCalibration(path, cal).ok());
  auto read = ReadCameraCalibration(path);
  std::filesystem::remove(path);
  ASSERT_TRUE(read.ok()) << read.status();
  EXPECT_EQ(read->source, "test");
  ASSERT_EQ(read->cameras.size(), 1u);
  ASSERT_NE(read->Find("mv-01"), nullptr);
  EXPECT_EQ(read->Find("hs-1"), nullptr);
  const CameraParameters a = Model().parameters(), b = read->cameras[0].model.parameters();
  EXPECT_EQ(a.width, b.width);
  EXPECT_EQ(a.fx, b.fx);
  EXPECT_EQ(a.cy, b.cy);
  EXPECT_EQ(a.distortion, b.distortion);
  EXPECT_EQ(a.position, b.position);
  EXPECT_EQ(a.rotation, b.rotation);
}

TEST(CameraCalibrationTest, ABrokenFileNamesTheFileAndTheField) {
  const std::string path = TempPath("broken");
  auto read_text = [&](const std::string& text) {
    EXPECT_TRUE(WriteFileAtomically(path, text).ok());
    auto r = ReadCameraCalibration(path);
    std::filesystem::remove(path);
    EXPECT_FALSE(r.ok());
    return std::string(r.status().message());
  };
  EXPECT_NE(read_text("{").find(path + ": not JSON"), std::string::npos);
  EXPECT_NE(read_text("{\"format\": \"x\"}").find("not a fastage-camera-calibration file"), std::string::npos);
  const std::string head = R"({"format": "fastage-camera-calibration", "version": 1, "cameras": [)";
  const std::string camera = R"({"id": "mv-01", "width": 10, "height": 10, "fx": 10, "fy": 10, "cx": 5, "cy": 5,
      "distortion": [0, 0, 0, 0, 0], "position_mm": [0, 0, 1000], "rotation": [1, 0, 0, 0, 1, 0, 0, 0, )";
  EXPECT_NE(read_text(head + camera + "-1]}]}").find("cameras[0] (\"mv-01\"): the rotation is not a rotation"),
            std::string::npos);
  EXPECT_NE(read_text(head + R"({"id": "mv-01", "width": 10})" + "]}").find("cameras[0].height: missing"),
            std::string::npos);
  EXPECT_NE(read_text(head + camera + "1]}, " + camera + "1]}]}").find("camera \"mv-01\" twice"), std::string::npos);
}

TEST(CameraCalibrationTest, AResizedModelSeesThePointWhereTheSensorDoes) {
  const CameraModel full = Model();
  const CameraModel small = full.Scaled(0.25);
  EXPECT_EQ(small.width(), 648);
  EXPECT_EQ(small.height(), 512);
  Eigen::Vector2d a, b;
  const Eigen::Vector3d p(20, 30, 1800);  // in front: the camera looks roughly along +z
  ASSERT_TRUE(full.Project(p, &a));
  ASSERT_TRUE(small.Project(p, &b));
  // Pixel corners scale: (a + 0.5) * s - 0.5.
  EXPECT_NEAR((a.x() + 0.5) * 0.25 - 0.5, b.x(), 1e-9);
  EXPECT_NEAR((a.y() + 0.5) * 0.25 - 0.5, b.y(), 1e-9);
}

}  // namespace
}  // namespace stage
