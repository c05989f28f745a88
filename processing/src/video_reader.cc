// The video reader module: see video_reader.h.
#include "video_reader.h"

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/videoio.hpp>

#include "absl/strings/str_cat.h"

namespace stage::processing::internal {
namespace {

absl::Status ReadVideo(const std::string& path, const FrameFn& fn) {
  cv::VideoCapture video(path);
  if (!video.isOpened()) return absl::NotFoundError(absl::StrCat(path, ": OpenCV cannot open it as a video"));
  cv::Mat frame, grey, values;
  for (int64_t index = 0; video.read(frame); ++index) {
    if (frame.channels() == 3) {
      cv::cvtColor(frame, grey, cv::COLOR_BGR2GRAY);
    } else {
      grey = frame;
    }
    grey.convertTo(values, CV_32F);  // continuous
    if (absl::Status s = fn(index, values.cols, values.rows, values.ptr<float>()); !s.ok()) return s;
  }
  return absl::OkStatus();
}

}  // namespace
}  // namespace stage::processing::internal

extern "C" __attribute__((visibility("default"))) stage::processing::internal::ReadVideoFn StageReadVideo() {
  return &stage::processing::internal::ReadVideo;
}
