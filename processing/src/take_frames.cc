// A cycle of a camera's take: see take_frames.h.
#include "stage/processing/take_frames.h"

#include <algorithm>
#include <filesystem>
#include <map>
#include <nlohmann/json.hpp>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "stage/common/status.h"
#include "stage/processing/calibration.h"
#include "stage/storage/frame_file.h"

namespace stage::processing {
namespace {

struct Format {
  Mosaic mosaic;
  int bits = 8;
};

absl::StatusOr<Format> ParseFormat(const std::string& path, const std::string& f, uint32_t bytes_per_pixel) {
  Format out;
  Mosaic& m = out.mosaic;
  if (absl::StartsWith(f, "BayerRG")) {
    m.red_x = 0, m.red_y = 0;
  } else if (absl::StartsWith(f, "BayerGR")) {
    m.red_x = 1, m.red_y = 0;
  } else if (absl::StartsWith(f, "BayerGB")) {
    m.red_x = 0, m.red_y = 1;
  } else if (absl::StartsWith(f, "BayerBG")) {
    m.red_x = 1, m.red_y = 1;
  } else if (absl::StartsWith(f, "Mono")) {
    m.mono = true;
  } else {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ": pixel format \"", f, "\" is not one photometric stereo reads"));
  }
  // The data bits are the name's last digits (Mono8, BayerRG12, ...); packed formats (...12p, ...Packed) are not
  // stored by the frame files.
  size_t digits = f.size();
  while (digits > 0 && absl::ascii_isdigit(static_cast<unsigned char>(f[digits - 1]))) --digits;
  if (digits == f.size() || !absl::SimpleAtoi(f.substr(digits), &out.bits) || out.bits < 8 || out.bits > 16) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ": pixel format \"", f, "\" is not one photometric stereo reads (8 to 16 bits, unpacked)"));
  }
  if ((bytes_per_pixel == 1) != (out.bits == 8)) {
    return absl::DataLossError(absl::StrCat(path, ": ", bytes_per_pixel, " bytes per pixel do not hold ", f));
  }
  return out;
}

// Mirrors an index into [0, n) without repeating the edge (-1 -> 1, n -> n - 2): the colour of a Bayer site keeps.
inline int Mirror(int i, int n) { return i < 0 ? -i : i >= n ? 2 * n - 2 - i : i; }

}  // namespace

namespace {

// What the file says each pattern index is must be the light model's pattern of that index.
absl::Status CheckPatterns(const std::string& path, const storage::FrameFileInfo& info, const LightModel& light) {
  const nlohmann::json names = nlohmann::json::parse(info.patterns_json, nullptr, /*allow_exceptions=*/false);
  if (!names.is_array() || names.empty()) {
    return absl::FailedPreconditionError(
        absl::StrCat(path, ": the file does not say which pattern each slot showed (no \"patterns\" attribute)"));
  }
  if (names.size() != light.patterns.size()) {
    return absl::FailedPreconditionError(
        absl::StrCat(path, ": its cycle has ", names.size(), " patterns, the light model ", light.patterns.size()));
  }
  for (size_t i = 0; i < names.size(); ++i) {
    const std::string name = names[i].is_object() ? names[i].value("name", "") : "";
    if (name != light.patterns[i].name) {
      return absl::FailedPreconditionError(absl::StrCat(path, ": pattern ", i, " is \"", name, "\" in the file, \"",
                                                        light.patterns[i].name, "\" in the light model"));
    }
  }
  return absl::OkStatus();
}

}  // namespace


void DemosaicBilinear(const float* mosaic, int width, int height, const Mosaic& layout, Image* rgb) {
  const int red_x = layout.red_x, red_y = layout.red_y;
  *rgb = Image(width, height, 3);
  auto at = [&](int x, int y) { return mosaic[static_cast<size_t>(Mirror(y, height)) * width + Mirror(x, width)]; };
  for (int y = 0; y < height; ++y) {
    const bool red_row = ((y ^ red_y) & 1) == 0;
    for (int x = 0; x < width; ++x) {
      const bool red_col = ((x ^ red_x) & 1) == 0;
      const float c = at(x, y);
      const float cross = 0.25f * (at(x - 1, y) + at(x + 1, y) + at(x, y - 1) + at(x, y + 1));
      const float diagonal = 0.25f * (at(x - 1, y - 1) + at(x + 1, y - 1) + at(x - 1, y + 1) + at(x + 1, y + 1));
      const float across = 0.5f * (at(x - 1, y) + at(x + 1, y));
      const float along = 0.5f * (at(x, y - 1) + at(x, y + 1));
      float* o = rgb->at(x, y);
      if (red_row && red_col) {  // red site
        o[0] = c, o[1] = cross, o[2] = diagonal;
      } else if (!red_row && !red_col) {  // blue site
        o[0] = diagonal, o[1] = cross, o[2] = c;
      } else if (red_row) {  // green between reds (left, right) and blues (up, down)
        o[0] = across, o[1] = c, o[2] = along;
      } else {  // green between blues (left, right) and reds (up, down)
        o[0] = along, o[1] = c, o[2] = across;
      }
    }
  }
}

absl::StatusOr<FrameFileShape> ReadFrameFileShape(const std::string& path) {
  auto file = storage::FrameFileReader::Open(path);
  if (!file.ok()) return file.status();
  const storage::FrameFileInfo& info = (*file)->info();
  auto format = ParseFormat(path, info.pixel_format, info.bytes_per_pixel);
  if (!format.ok()) return format.status();
  FrameFileShape shape;
  shape.width = static_cast<int>(info.width);
  shape.height = static_cast<int>(info.height);
  shape.bits = format->bits;
  shape.camera_id = info.camera_id;
  shape.pixel_format = info.pixel_format;
  auto records = (*file)->Records();
  if (!records.ok()) return records.status();
  for (const storage::FrameRecord& r : *records) {
    if (r.status == storage::FrameStatus::kOk) shape.last_slot = std::max(shape.last_slot, r.slot);
  }
  return shape;
}

absl::StatusOr<CycleFrames> LoadCycle(const std::string& path, int64_t frame, const LightModel& light) {
  auto file = storage::FrameFileReader::Open(path);
  if (!file.ok()) return file.status();
  const storage::FrameFileInfo& info = (*file)->info();
  auto format = ParseFormat(path, info.pixel_format, info.bytes_per_pixel);
  if (!format.ok()) return format.status();
  CycleFrames out;
  out.camera_id = info.camera_id;
  out.pixel_format = info.pixel_format;
  out.bits = format->bits;
  out.mosaic = format->mosaic;
  out.width = static_cast<int>(info.width);
  out.height = static_cast<int>(info.height);
  if (out.width < 2 || out.height < 2) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": frames of ", out.width, "x", out.height,
                                                   " are too small to demosaic (2x2 at least)"));
  }
  STAGE_RETURN_IF_ERROR(CheckPatterns(path, info, light));
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
  const size_t n = static_cast<size_t>(out.width) * out.height;
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
    const uint8_t* bytes = pixels->data();
    std::vector<uint16_t> raw(n);
    for (size_t i = 0; i < n; ++i) {
      raw[i] = out.bits == 8 ? bytes[i] : static_cast<uint16_t>(bytes[2 * i] | (bytes[2 * i + 1] << 8));
    }
    out.raw.push_back(std::move(raw));
    out.slots.push_back(slot);
  }
  return out;
}

absl::StatusOr<std::vector<Image>> DemosaicCycle(const CycleFrames& cycle, const RawCorrection& correction) {
  const int w = cycle.width, h = cycle.height;
  if (correction.flat_field != nullptr &&
      (correction.flat_field->width != w || correction.flat_field->height != h ||
       correction.flat_field->channels != 1)) {
    return absl::InvalidArgumentError(absl::StrCat("camera \"", cycle.camera_id, "\": the flat field is ",
                                                   correction.flat_field->width, "x", correction.flat_field->height,
                                                   "x", correction.flat_field->channels, ", the frames ", w, "x", h,
                                                   "x1"));
  }
  std::vector<float> mosaic(static_cast<size_t>(w) * h);
  const float black = static_cast<float>(correction.black_level_dn);
  std::vector<Image> out;
  for (const std::vector<uint16_t>& raw : cycle.raw) {
    for (size_t i = 0; i < mosaic.size(); ++i) {
      float v = static_cast<float>(raw[i]) - black;
      if (correction.flat_field != nullptr) v /= correction.flat_field->pixels[i];
      mosaic[i] = v;
    }
    Image img;
    if (cycle.mosaic.mono) {
      img = Image(w, h, 3);
      for (size_t i = 0; i < mosaic.size(); ++i) {
        img.pixels[3 * i] = img.pixels[3 * i + 1] = img.pixels[3 * i + 2] = mosaic[i];
      }
    } else {
      DemosaicBilinear(mosaic.data(), w, h, cycle.mosaic, &img);
    }
    out.push_back(std::move(img));
  }
  return out;
}

}  // namespace stage::processing

namespace stage::processing {

absl::Status ForEachFullLitFrame(const std::string& path, int64_t first, int64_t last, const LightModel& light,
                                 double black_level_dn,
                                 const std::function<absl::Status(int64_t frame, const Image& grey)>& visit) {
  auto file = storage::FrameFileReader::Open(path);
  if (!file.ok()) return file.status();
  const storage::FrameFileInfo& info = (*file)->info();
  auto format = ParseFormat(path, info.pixel_format, info.bytes_per_pixel);
  if (!format.ok()) return format.status();
  STAGE_RETURN_IF_ERROR(CheckPatterns(path, info, light));
  // The full-on patterns (every unit at 1), cross-polarized first: the least specular glare.
  std::vector<int64_t> full;
  for (int pass = 0; pass < 2; ++pass) {
    for (size_t p = 0; p < light.patterns.size(); ++p) {
      const LightPattern& pattern = light.patterns[p];
      const bool all_on = !pattern.weights.empty() &&
                          std::all_of(pattern.weights.begin(), pattern.weights.end(), [](double w) { return w > 0.999; });
      if (all_on && pattern.parallel == (pass == 1)) full.push_back(static_cast<int64_t>(p));
    }
  }
  if (full.empty()) return absl::FailedPreconditionError(absl::StrCat(path, ": the pattern set has no full-on pattern"));
  auto records = (*file)->Records();
  if (!records.ok()) return records.status();
  const auto cycle = static_cast<int64_t>(light.patterns.size());
  std::map<int64_t, int64_t> index_of_slot;
  for (size_t i = 0; i < records->size(); ++i) {
    const storage::FrameRecord& r = (*records)[i];
    if (r.status == storage::FrameStatus::kOk) index_of_slot[r.slot] = static_cast<int64_t>(i);
  }
  const int w = static_cast<int>(info.width), h = static_cast<int>(info.height);
  if (w < 2 || h < 2) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": frames of ", w, "x", h, " are too small (2x2 at least)"));
  }
  const size_t n = static_cast<size_t>(w) * h;
  std::vector<float> mosaic(n);
  Image rgb, grey(w, h, 1);
  for (int64_t frame = first; frame < last; ++frame) {
    int64_t index = -1;
    for (int64_t p : full) {
      auto it = index_of_slot.find(frame * cycle + p);
      if (it != index_of_slot.end()) {
        index = it->second;
        break;
      }
    }
    if (index < 0) continue;  // none recorded in this frame (lost, or the camera fires on other patterns)
    auto pixels = (*file)->Pixels(index);
    if (!pixels.ok()) return pixels.status();
    const uint8_t* bytes = pixels->data();
    for (size_t i = 0; i < n; ++i) {
      const float v = format->bits == 8 ? bytes[i] : static_cast<float>(bytes[2 * i] | (bytes[2 * i + 1] << 8));
      mosaic[i] = v - static_cast<float>(black_level_dn);
    }
    if (format->mosaic.mono) {
      grey.pixels = mosaic;
    } else {
      DemosaicBilinear(mosaic.data(), w, h, format->mosaic, &rgb);
      for (size_t i = 0; i < n; ++i) {
        grey.pixels[i] = (rgb.pixels[3 * i] + rgb.pixels[3 * i + 1] + rgb.pixels[3 * i + 2]) / 3.0f;
      }
    }
    STAGE_RETURN_IF_ERROR(visit(frame, grey));
  }
  return absl::OkStatus();
}

}  // namespace stage::processing

namespace stage::processing {

absl::StatusOr<std::vector<TakeCamera>> OpenTakeCameras(const std::string& take_dir, const LoadedRig& rig,
                                                        const std::vector<std::string>& ids,
                                                        const CameraCalibration* calibration) {
  std::vector<TakeCamera> out;
  for (const std::string& id : ids) {
    TakeCamera c;
    c.id = id;
    for (const v1::CameraConfig& config : rig.rig.cameras()) {
      if (config.id() == id) c.black_level_dn = config.photometric().black_level_dn();
    }
    c.path = take_dir + "/cameras/" + id + ".h5";
    if (!std::filesystem::exists(c.path)) {
      return absl::NotFoundError(absl::StrCat(c.path, ": no frame file for camera \"", id, "\" in the take"));
    }
    STAGE_ASSIGN_OR_RETURN(const FrameFileShape shape, ReadFrameFileShape(c.path));
    STAGE_ASSIGN_OR_RETURN(c.model, CameraAtImageSize(rig, id, shape.width, shape.height, calibration));
    c.last_slot = shape.last_slot;
    out.push_back(std::move(c));
  }
  return out;
}

}  // namespace stage::processing
