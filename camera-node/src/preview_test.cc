// Previews: a frame shrunk and PNG-encoded that a PNG reader (libpng's own) decodes back to the frame's picture.
#include "preview.h"

#include <png.h>

#include <string>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace stage::camera {
namespace {

// A 16-bit 640 x 400 frame: a horizontal ramp from 0 to 4000 (12-bit data in 16-bit words).
Frame Ramp() {
  Frame f;
  f.width = 640;
  f.height = 400;
  f.pixel_format = "Mono16";
  f.data.resize(2 * f.width * f.height);
  for (uint32_t y = 0; y < f.height; ++y) {
    for (uint32_t x = 0; x < f.width; ++x) {
      const auto v = static_cast<uint16_t>(4000 * x / (f.width - 1));
      f.data[2 * (y * f.width + x)] = static_cast<uint8_t>(v & 0xff);
      f.data[2 * (y * f.width + x) + 1] = static_cast<uint8_t>(v >> 8);
    }
  }
  return f;
}

TEST(PreviewTest, APngReaderGetsTheShrunkFrameBack) {
  auto preview = MakePreview(Ramp(), 256);
  ASSERT_TRUE(preview.ok()) << preview.status();
  EXPECT_EQ(preview->width(), 256u);
  EXPECT_EQ(preview->height(), 160u);
  const std::string& png = preview->png();
  png_image image{};
  image.version = PNG_IMAGE_VERSION;
  ASSERT_TRUE(png_image_begin_read_from_memory(&image, png.data(), png.size())) << image.message;
  EXPECT_EQ(image.width, 256u);
  EXPECT_EQ(image.height, 160u);
  image.format = PNG_FORMAT_GRAY;
  std::vector<uint8_t> grey(PNG_IMAGE_SIZE(image));
  ASSERT_TRUE(png_image_finish_read(&image, nullptr, grey.data(), 0, nullptr)) << image.message;
  // Scaled by the frame's peak: the ramp runs from 0 to 255 across every row.
  for (int y : {0, 80, 159}) {
    EXPECT_LE(grey[y * 256], 2) << "row " << y;
    EXPECT_GE(grey[y * 256 + 255], 253) << "row " << y;
    EXPECT_NEAR(grey[y * 256 + 128], 128, 2) << "row " << y;
  }
}

TEST(PreviewTest, AnEmptyFrameIsRefused) {
  Frame f;
  f.width = 10;
  f.height = 10;
  EXPECT_EQ(MakePreview(f, 256).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace stage::camera
