// Photometric maps on disk: see map_files.h.
#include "stage/processing/map_files.h"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"
#include "contact_sheet.h"
#include "stage/common/file_util.h"

namespace stage::processing {
namespace {

// OpenCV reads and writes OpenEXR only when asked to (a guard against untrusted files); these are our own.
void EnableExr() { setenv("OPENCV_IO_ENABLE_OPENEXR", "1", 0); }

absl::Status Write(const std::string& path, const cv::Mat& image, const std::vector<int>& params = {}) {
  bool ok = false;
  try {
    ok = cv::imwrite(path, image, params);
  } catch (const cv::Exception& e) {
    return absl::UnavailableError(absl::StrCat(path, ": ", e.what()));
  }
  if (!ok) return absl::UnavailableError(absl::StrCat(path, ": cannot write the image"));
  return absl::OkStatus();
}

// OpenCV's channel order is B, G, R(, A): values x, y, z (R, G, B) go in reversed, alpha stays last. The channel of
// OpenCV's that holds value `c` of `channels`.
int CvChannel(int c, int channels) { return channels == 4 ? (c < 3 ? 2 - c : 3) : channels - 1 - c; }

cv::Mat ToMat(const Image& image) {
  cv::Mat m(image.height, image.width, CV_32FC(image.channels));
  for (int y = 0; y < image.height; ++y) {
    float* row = m.ptr<float>(y);
    for (int x = 0; x < image.width; ++x) {
      const float* v = image.at(x, y);
      for (int c = 0; c < image.channels; ++c) row[x * image.channels + CvChannel(c, image.channels)] = v[c];
    }
  }
  return m;
}

uint8_t Byte(float v) { return static_cast<uint8_t>(std::clamp(std::lround(v * 255.f), 0L, 255L)); }

float Srgb(float linear) {
  linear = std::clamp(linear, 0.f, 1.f);
  return linear <= 0.0031308f ? 12.92f * linear : 1.055f * std::pow(linear, 1 / 2.4f) - 0.055f;
}

// An 8-bit preview (BGR) of a scalar over [0, full].
cv::Mat ScalarPreview(const Image& s, float full) {
  cv::Mat m(s.height, s.width, CV_8UC3);
  for (int y = 0; y < s.height; ++y) {
    for (int x = 0; x < s.width; ++x) {
      const uint8_t b = Byte(s.at(x, y)[0] / full);
      m.at<cv::Vec3b>(y, x) = {b, b, b};
    }
  }
  return m;
}

}  // namespace

cv::Mat NormalPreview(const Image& n, const cv::Vec3b& empty) {
  cv::Mat m(n.height, n.width, CV_8UC3, cv::Scalar(empty[0], empty[1], empty[2]));
  for (int y = 0; y < n.height; ++y) {
    for (int x = 0; x < n.width; ++x) {
      const float* v = n.at(x, y);
      if (v[0] == 0 && v[1] == 0 && v[2] == 0) continue;
      m.at<cv::Vec3b>(y, x) = {Byte((v[2] + 1) / 2), Byte((v[1] + 1) / 2), Byte((v[0] + 1) / 2)};
    }
  }
  return m;
}

cv::Mat AlbedoPreview(const Image& a) {
  cv::Mat m(a.height, a.width, CV_8UC3);
  for (int y = 0; y < a.height; ++y) {
    for (int x = 0; x < a.width; ++x) {
      const float* v = a.at(x, y);
      m.at<cv::Vec3b>(y, x) = {Byte(Srgb(v[2])), Byte(Srgb(v[1])), Byte(Srgb(v[0]))};
    }
  }
  return m;
}

cv::Mat ContactSheet(const std::vector<std::pair<std::string, cv::Mat>>& tiles, const std::string& title, int columns) {
  const int w = tiles[0].second.cols, h = tiles[0].second.rows;
  const int scale = std::max(1, (256 + w - 1) / w);
  const int tw = w * scale, th = h * scale, label = 22, header = 30;
  const int rows = (static_cast<int>(tiles.size()) + columns - 1) / columns;
  cv::Mat sheet(header + rows * (th + label), columns * tw, CV_8UC3, cv::Scalar::all(24));
  cv::putText(sheet, title, {6, 21}, cv::FONT_HERSHEY_SIMPLEX, 0.55, cv::Scalar::all(235), 1, cv::LINE_AA);
  for (size_t i = 0; i < tiles.size(); ++i) {
    const int cx = static_cast<int>(i) % columns * tw, cy = header + static_cast<int>(i) / columns * (th + label);
    cv::Mat big;
    cv::resize(tiles[i].second, big, {tw, th}, 0, 0, cv::INTER_NEAREST);
    big.copyTo(sheet(cv::Rect(cx, cy + label, tw, th)));
    cv::putText(sheet, tiles[i].first, {cx + 4, cy + 16}, cv::FONT_HERSHEY_SIMPLEX, 0.45, cv::Scalar::all(235), 1,
                cv::LINE_AA);
  }
  return sheet;
}

absl::Status WriteExr(const std::string& path, const Image& image) {
  EnableExr();
  return Write(path, ToMat(image), {cv::IMWRITE_EXR_TYPE, cv::IMWRITE_EXR_TYPE_FLOAT});
}

absl::StatusOr<Image> ReadImageFile(const std::string& path) {
  EnableExr();
  cv::Mat m;
  try {
    m = cv::imread(path, cv::IMREAD_UNCHANGED);
  } catch (const cv::Exception& e) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": ", e.what()));
  }
  if (m.empty()) return absl::NotFoundError(absl::StrCat(path, ": cannot read the image"));
  const int channels = m.channels();
  if (channels != 1 && channels != 3 && channels != 4) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": ", channels, " channels; 1, 3 or 4 expected"));
  }
  double scale = 1;
  if (m.depth() == CV_8U) scale = 1.0 / 255;
  if (m.depth() == CV_16U) scale = 1.0 / 32768;  // a flat field's 1 (calibration.h)
  cv::Mat f;
  m.convertTo(f, CV_32F, scale);
  Image out(f.cols, f.rows, channels);
  for (int y = 0; y < f.rows; ++y) {
    const float* row = f.ptr<float>(y);
    for (int x = 0; x < f.cols; ++x) {
      float* o = out.at(x, y);
      for (int c = 0; c < channels; ++c) o[c] = row[x * channels + CvChannel(c, channels)];
    }
  }
  return out;
}

absl::Status WriteTextureFiles(const std::string& dir, const std::vector<std::pair<std::string, const Image*>>& exr,
                               const std::string& metrics_json, const std::string& title) {
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) return absl::UnavailableError(absl::StrCat(dir, ": ", ec.message()));
  std::vector<std::pair<std::string, cv::Mat>> previews;
  for (const auto& [name, image] : exr) {
    if (auto s = WriteExr(dir + "/" + name + ".exr", *image); !s.ok()) return s;
    cv::Mat preview;
    std::string caption = name;
    if (name == "albedo") {
      preview = AlbedoPreview(*image);
      caption = "diffuse albedo (sRGB)";
    } else if (name == "normal_tangent") {
      preview = NormalPreview(*image);
      caption = "diffuse normal (tangent space)";
    } else if (name == "specular") {
      preview = ScalarPreview(*image, 0.1f);
      caption = "specular intensity (0..0.1)";
    } else if (name == "roughness") {
      preview = ScalarPreview(*image, 1.f);
      caption = "roughness (GGX alpha, 0..1)";
    } else {
      continue;
    }
    if (auto s = Write(dir + "/" + name + ".png", preview); !s.ok()) return s;
    previews.emplace_back(caption, preview);
  }
  if (auto s = Write(dir + "/contact_sheet.png", ContactSheet(previews, title)); !s.ok()) return s;
  return WriteFileAtomically(dir + "/metrics.json", metrics_json + "\n");
}

absl::Status WriteGeometryFiles(const std::string& dir, const PixelGeometry& geometry,
                                const PhotometricCamera& camera) {
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) return absl::UnavailableError(absl::StrCat(dir, ": ", ec.message()));
  const int w = geometry.width, h = geometry.height;
  Image depth(w, h, 1);
  cv::Mat placed(h, w, CV_8U, cv::Scalar(0));
  const Eigen::Matrix3f rotation = camera.world_to_camera.cast<float>();
  const Eigen::Vector3f origin = camera.position_mm.cast<float>();
  for (size_t i = 0; i < static_cast<size_t>(w) * h; ++i) {
    if (!geometry.Covers(i)) continue;
    const Eigen::Vector3f point = Eigen::Map<const Eigen::Vector3f>(&geometry.points[3 * i]);
    depth.pixels[i] = (rotation * (point - origin)).z();
    if (!geometry.placed.empty() && geometry.placed[i]) placed.at<uint8_t>(static_cast<int>(i)) = 255;
  }
  if (auto s = WriteExr(dir + "/geometry_depth.exr", depth); !s.ok()) return s;
  return Write(dir + "/geometry_placed.png", placed);
}

absl::Status WriteMapFiles(const std::string& dir, const PhotometricMaps& maps, const std::string& metrics_json,
                           const std::string& title) {
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) return absl::UnavailableError(absl::StrCat(dir, ": ", ec.message()));
  const std::vector<std::pair<std::string, const Image*>> exr = {
      {"diffuse_normal_world", &maps.diffuse_normal_world},
      {"diffuse_normal_camera", &maps.diffuse_normal_camera},
      {"specular_normal_world", &maps.specular_normal_world},
      {"specular_normal_camera", &maps.specular_normal_camera},
      {"albedo", &maps.albedo},
      {"specular", &maps.specular},
      {"roughness", &maps.roughness},
      {"confidence", &maps.confidence}};
  for (const auto& [name, image] : exr) {
    if (auto s = WriteExr(dir + "/" + name + ".exr", *image); !s.ok()) return s;
  }
  cv::Mat flags(maps.height, maps.width, CV_8U, const_cast<uint8_t*>(maps.flags.data()));
  if (auto s = Write(dir + "/flags.png", flags); !s.ok()) return s;
  // Previews: specular intensity 0..0.1, roughness 0..1, confidence 0..1.
  const std::vector<std::pair<std::string, cv::Mat>> previews = {
      {"diffuse normal (stage)", NormalPreview(maps.diffuse_normal_world)},
      {"specular normal (stage)", NormalPreview(maps.specular_normal_world)},
      {"diffuse albedo (sRGB)", AlbedoPreview(maps.albedo)},
      {"specular intensity (0..0.1)", ScalarPreview(maps.specular, 0.1f)},
      {"roughness (GGX alpha, 0..1)", ScalarPreview(maps.roughness, 1.f)},
      {"confidence (0..1)", ScalarPreview(maps.confidence, 1.f)}};
  const char* files[] = {
      "diffuse_normal_world", "specular_normal_world", "albedo", "specular", "roughness", "confidence"};
  for (size_t i = 0; i < previews.size(); ++i) {
    if (auto s = Write(dir + "/" + files[i] + ".png", previews[i].second); !s.ok()) return s;
  }
  if (auto s = Write(dir + "/contact_sheet.png", ContactSheet(previews, title)); !s.ok()) return s;
  std::ofstream out(dir + "/metrics.json");
  out << metrics_json << "\n";
  out.close();
  if (!out) return absl::DataLossError(absl::StrCat(dir, "/metrics.json: cannot write"));
  return absl::OkStatus();
}

}  // namespace stage::processing
