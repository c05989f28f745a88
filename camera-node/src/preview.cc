// Previews: see preview.h.
#include "preview.h"

#include <png.h>

#include <algorithm>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <string>

#include "absl/strings/str_cat.h"

namespace stage::camera {
namespace {

// An 8-bit grey image as PNG, by libpng's simplified API (OpenCV's encoder would bring its image codecs, GDAL and 80
// more libraries, into every camera node's start).
absl::StatusOr<std::string> EncodePng(const cv::Mat& grey) {
  png_image image{};
  image.version = PNG_IMAGE_VERSION;
  image.width = static_cast<png_uint_32>(grey.cols);
  image.height = static_cast<png_uint_32>(grey.rows);
  image.format = PNG_FORMAT_GRAY;
  const auto stride = static_cast<png_int_32>(grey.step);
  png_alloc_size_t size = 0;
  std::string png;
  // The first call sizes the buffer, the second fills it.
  if (png_image_write_to_memory(&image, nullptr, &size, 0, grey.data, stride, nullptr)) {
    png.resize(size);
    if (png_image_write_to_memory(&image, png.data(), &size, 0, grey.data, stride, nullptr)) {
      png.resize(size);
      return png;
    }
  }
  const std::string why = image.message;
  png_image_free(&image);
  return absl::InternalError(absl::StrCat("preview: PNG encoding failed: ", why));
}

}  // namespace

absl::StatusOr<v1::Preview> MakePreview(const Frame& frame, uint32_t max_size) {
  const size_t pixels = static_cast<size_t>(frame.width) * frame.height;
  if (pixels == 0 || frame.pixels().size() < pixels || max_size == 0) {
    return absl::InvalidArgumentError(absl::StrCat("preview of a ", frame.width, "x", frame.height, " frame of ",
                                                   frame.pixels().size(), " bytes at most ", max_size, " px"));
  }
  const bool wide = frame.pixels().size() >= 2 * pixels;
  const int h = static_cast<int>(frame.height), w = static_cast<int>(frame.width);
  cv::Mat src(h, w, wide ? CV_16UC1 : CV_8UC1, const_cast<uint8_t*>(frame.pixels().data()));
  cv::Mat eight;
  if (wide) {
    double peak = 0;
    cv::minMaxLoc(src, nullptr, &peak);
    src.convertTo(eight, CV_8U, peak > 0 ? 255.0 / peak : 0);
  } else {
    eight = src;
  }
  const double scale = std::min(1.0, static_cast<double>(max_size) / std::max(w, h));
  cv::Mat small;
  cv::resize(eight, small, cv::Size(std::max(1, static_cast<int>(w * scale)), std::max(1, static_cast<int>(h * scale))),
             0, 0, cv::INTER_AREA);
  auto png = EncodePng(small);
  if (!png.ok()) return png.status();
  v1::Preview preview;
  preview.set_width(static_cast<uint32_t>(small.cols));
  preview.set_height(static_cast<uint32_t>(small.rows));
  preview.set_png(*std::move(png));
  return preview;
}

}  // namespace stage::camera
