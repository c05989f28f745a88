// The image decoder module: see image_decoder.h.
#include "image_decoder.h"

#include <cstdlib>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

namespace stage::sim::internal {
namespace {

absl::Status Decode(const std::string& path, int channels, DecodedImage* out) {
  setenv("OPENCV_IO_ENABLE_OPENEXR", "1", 0);
  cv::Mat m = cv::imread(path, cv::IMREAD_UNCHANGED);
  if (m.empty()) return absl::InvalidArgumentError("cannot read it (missing, or not PNG, JPEG, TIFF or OpenEXR)");
  double scale = 1;
  out->integer = true;
  switch (m.depth()) {
    case CV_8U:
      scale = 1.0 / 255;
      break;
    case CV_16U:
      scale = 1.0 / 65535;
      break;
    case CV_32F:
      out->integer = false;
      break;
    default:
      return absl::InvalidArgumentError("neither 8 nor 16-bit nor float");
  }
  cv::Mat f;
  m.convertTo(f, CV_32F, scale);
  if (f.channels() == 4) cv::cvtColor(f, f, cv::COLOR_BGRA2BGR);
  if (channels == 1 && f.channels() == 3) cv::cvtColor(f, f, cv::COLOR_BGR2GRAY);
  if (channels == 3 && f.channels() == 1) cv::cvtColor(f, f, cv::COLOR_GRAY2BGR);
  if (channels == 3) cv::cvtColor(f, f, cv::COLOR_BGR2RGB);
  out->width = f.cols;
  out->height = f.rows;
  out->texels.assign(f.ptr<float>(0), f.ptr<float>(0) + static_cast<size_t>(f.total()) * channels);
  return absl::OkStatus();
}

}  // namespace
}  // namespace stage::sim::internal

extern "C" __attribute__((visibility("default"))) stage::sim::internal::DecodeImageFn StageSimDecodeImage() {
  return &stage::sim::internal::Decode;
}
