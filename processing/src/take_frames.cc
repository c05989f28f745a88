// A cycle of a camera's take: see take_frames.h.
#include "stage/processing/take_frames.h"

#include <map>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "stage/storage/frame_file.h"

namespace stage::processing {

absl::StatusOr<CycleFrames> LoadCycle(const std::string& path, int64_t frame, const LightModel& light,
                                      double black_level_dn) {
  auto file = storage::FrameFileReader::Open(path);
  if (!file.ok()) return file.status();
  const storage::FrameFileInfo& info = (*file)->info();
  CycleFrames out;
  out.camera_id = info.camera_id;
  out.pixel_format = info.pixel_format;
  const std::string& f = info.pixel_format;
  int code = -1;  // OpenCV's demosaicing code; -1: mono
  if (absl::StartsWith(f, "BayerRG"))
    code = cv::COLOR_BayerBG2BGR;  // GenICam BayerRG is OpenCV's BayerBG, etc.
  else if (absl::StartsWith(f, "BayerGR"))
    code = cv::COLOR_BayerGB2BGR;
  else if (absl::StartsWith(f, "BayerGB"))
    code = cv::COLOR_BayerGR2BGR;
  else if (absl::StartsWith(f, "BayerBG"))
    code = cv::COLOR_BayerRG2BGR;
  else if (!absl::StartsWith(f, "Mono")) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ": pixel format \"", f, "\" is not one photometric stereo reads"));
  }
  out.bits = absl::EndsWith(f, "8") ? 8 : absl::EndsWith(f, "12") ? 12 : 16;
  if ((info.bytes_per_pixel == 1) != (out.bits == 8)) {
    return absl::DataLossError(absl::StrCat(path, ": ", info.bytes_per_pixel, " bytes per pixel do not hold ", f));
  }
  // What the file says each pattern index is must be the light model's pattern of that index.
  const nlohmann::json names = nlohmann::json::parse(info.patterns_json, nullptr, /*allow_exceptions=*/false);
  if (names.is_array() && !names.empty()) {
    if (names.size() != light.patterns.size()) {
      return absl::FailedPreconditionError(
          absl::StrCat(path, ": its cycle has ", names.size(), " patterns, the light model ", light.patterns.size()));
    }
    for (size_t i = 0; i < names.size(); ++i) {
      const std::string name = names[i].value("name", "");
      if (name != light.patterns[i].name) {
        return absl::FailedPreconditionError(absl::StrCat(path, ": pattern ", i, " is \"", name, "\" in the file, \"",
                                                          light.patterns[i].name, "\" in the light model"));
      }
    }
  }
  auto records = (*file)->Records();
  if (!records.ok()) return records.status();
  const auto cycle = static_cast<int64_t>(light.patterns.size());
  std::map<int64_t, int64_t> index_of_slot;  // slot -> frame index in the file
  for (size_t i = 0; i < records->size(); ++i) {
    const storage::FrameRecord& r = (*records)[i];
    if (r.slot >= frame * cycle && r.slot < (frame + 1) * cycle && r.status == storage::FrameStatus::kOk) {
      index_of_slot[r.slot] = static_cast<int64_t>(i);
    }
  }
  const int w = static_cast<int>(info.width), h = static_cast<int>(info.height);
  for (int64_t p = 0; p < cycle; ++p) {
    const int64_t slot = frame * cycle + p;
    auto it = index_of_slot.find(slot);
    if (it == index_of_slot.end()) {
      return absl::NotFoundError(absl::StrCat(path, ": frame ", frame, " has no image of pattern \"",
                                              light.patterns[static_cast<size_t>(p)].name, "\" (slot ", slot,
                                              "): lost in the take, or not recorded"));
    }
    auto pixels = (*file)->Pixels(it->second);
    if (!pixels.ok()) return pixels.status();
    cv::Mat raw(h, w, out.bits == 8 ? CV_8U : CV_16U, pixels->data());
    cv::Mat bgr;
    if (code < 0) {
      cv::cvtColor(raw, bgr, cv::COLOR_GRAY2BGR);
    } else {
      cv::cvtColor(raw, bgr, code);
    }
    cv::Mat rgb;
    bgr.convertTo(rgb, CV_32FC3, 1.0, -black_level_dn);
    Image img(w, h, 3);
    for (int y = 0; y < h; ++y) {
      const cv::Vec3f* row = rgb.ptr<cv::Vec3f>(y);
      for (int x = 0; x < w; ++x) {
        float* o = img.at(x, y);
        o[0] = row[x][2];
        o[1] = row[x][1];
        o[2] = row[x][0];
      }
    }
    out.images.push_back(std::move(img));
    out.slots.push_back(slot);
  }
  return out;
}

}  // namespace stage::processing
