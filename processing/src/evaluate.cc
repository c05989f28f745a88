// Photometric results against ground truth: see evaluate.h.
#include "stage/processing/evaluate.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <regex>
#include <set>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/processing/map_files.h"
#include "stage/processing/photometric_stage.h"
#include "statistics.h"

namespace stage::processing {
namespace {

namespace fs = std::filesystem;

constexpr double kDeg = 180.0 / M_PI;

// Every channel blurred by a Gaussian over the mask only (normalized convolution), so that the background does not
// bleed into the subject's edge.
Image MaskedBlur(const Image& in, const std::vector<uint8_t>& mask, double sigma) {
  cv::Mat weight(in.height, in.width, CV_32F);
  for (int i = 0; i < in.width * in.height; ++i) weight.at<float>(i) = mask[static_cast<size_t>(i)] ? 1.f : 0.f;
  cv::Mat wb;
  cv::GaussianBlur(weight, wb, {0, 0}, sigma, sigma, cv::BORDER_REFLECT);
  Image out(in.width, in.height, in.channels);
  for (int c = 0; c < in.channels; ++c) {
    cv::Mat ch(in.height, in.width, CV_32F), blurred;
    for (int i = 0; i < in.width * in.height; ++i) {
      ch.at<float>(i) = mask[static_cast<size_t>(i)] ? in.pixels[static_cast<size_t>(i) * in.channels + c] : 0.f;
    }
    cv::GaussianBlur(ch, blurred, {0, 0}, sigma, sigma, cv::BORDER_REFLECT);
    for (int i = 0; i < in.width * in.height; ++i) {
      const float w = wb.at<float>(i);
      out.pixels[static_cast<size_t>(i) * in.channels + c] = w > 1e-6f ? blurred.at<float>(i) / w : 0.f;
    }
  }
  return out;
}

constexpr uint8_t kUnsplit = 0xff;  // a pixel's class when the figures are not split by geometry

struct Samples {
  std::vector<double> error, band, floor;
  std::vector<double> confident;  // error of the pixels the solver is confident in
  std::vector<uint8_t> geometry;  // each error's GeometryClass (kUnsplit: none)
  int64_t mask = 0;
};

double Mean(const std::vector<double>& v) {
  double s = 0;
  for (double x : v) s += x;
  return v.empty() ? 0 : s / static_cast<double>(v.size());
}

bool Zero(const float* v, int channels) {
  for (int c = 0; c < channels; ++c) {
    if (v[c] != 0) return false;
  }
  return true;
}

// Compares one map. kind: 0 normal (angle), 1 relative, 2 absolute. `doubtful`: per pixel, 1 where the solver
// flagged it (its error is left out of the confident figures).
void Compare(const Image& est, const Image& truth, const std::vector<uint8_t>& mask,
             const std::vector<uint8_t>& doubtful, const std::vector<uint8_t>& geometry, int kind, double sigma,
             Samples* out) {
  // Where both have a value.
  std::vector<uint8_t> valid(mask.size(), 0);
  for (size_t i = 0; i < mask.size(); ++i) {
    if (!mask[i]) continue;
    ++out->mask;
    const float* e = &est.pixels[i * est.channels];
    if (kind == 0 && Zero(e, 3)) continue;
    if (kind != 0 && !std::isfinite(e[0])) continue;  // not solved there
    valid[i] = 1;
  }
  const Image est_low = MaskedBlur(est, valid, sigma), truth_low = MaskedBlur(truth, valid, sigma);
  const int ch = est.channels;
  for (size_t i = 0; i < valid.size(); ++i) {
    if (!valid[i]) continue;
    const float* e = &est.pixels[i * ch];
    const float* t = &truth.pixels[i * ch];
    const float* el = &est_low.pixels[i * ch];
    const float* tl = &truth_low.pixels[i * ch];
    out->geometry.push_back(geometry[i]);
    if (kind == 0) {
      const Eigen::Vector3d a(e[0], e[1], e[2]), b(t[0], t[1], t[2]);
      out->error.push_back(std::atan2(a.cross(b).norm(), a.dot(b)) * kDeg);
      // High-pass parts of the unit vectors (radians for small angles).
      Eigen::Vector3d he, ht;
      for (int c = 0; c < 3; ++c) {
        he[c] = e[c] - el[c];
        ht[c] = t[c] - tl[c];
      }
      out->band.push_back((he - ht).norm() * kDeg);
      out->floor.push_back(ht.norm() * kDeg);
      if (!doubtful[i]) out->confident.push_back(out->error.back());
    } else {
      double err = 0, band = 0, floor = 0;
      for (int c = 0; c < ch; ++c) {
        const double scale = kind == 1 ? std::max(1e-6f, std::abs(t[c])) : 1.0;
        const double low = kind == 1 ? std::max(1e-6f, std::abs(tl[c])) : 1.0;
        err += std::abs(e[c] - t[c]) / scale;
        band += std::abs((e[c] - el[c]) - (t[c] - tl[c])) / low;
        floor += std::abs(t[c] - tl[c]) / low;
      }
      const double unit = kind == 1 ? 100.0 : 1.0;
      out->error.push_back(unit * err / ch);
      out->band.push_back(unit * band / ch);
      out->floor.push_back(unit * floor / ch);
      if (!doubtful[i]) out->confident.push_back(out->error.back());
    }
  }
}

// Each mask pixel's GeometryClass from the geometry files in `dir` (WriteGeometryFiles) against the truth's depth.exr
// in `truth_dir`; the absolute depth errors of the pixels with a point go to `depth_errors` by class.
// `mask`: width x height, the truth's subject mask.
absl::StatusOr<std::vector<uint8_t>> ClassifyGeometry(const std::string& dir, const std::string& truth_dir,
                                                      const std::vector<uint8_t>& mask, int width, int height,
                                                      double off_mm,
                                                      std::vector<double> depth_errors[kGeometryClasses]) {
  std::vector<Image> images;
  for (const std::string& path :
       {dir + "/geometry_depth.exr", dir + "/geometry_placed.png", truth_dir + "/depth.exr"}) {
    auto image = ReadImageFile(path);
    if (!image.ok()) return image.status();
    if (image->width != width || image->height != height || image->channels != 1) {
      return absl::FailedPreconditionError(absl::StrCat(path, " is ", image->width, "x", image->height, "x",
                                                        image->channels, ", the subject mask ", width, "x", height,
                                                        "x1"));
    }
    images.push_back(std::move(*image));
  }
  const Image *depth = &images[0], *placed = &images[1], *truth = &images[2];
  std::vector<uint8_t> classes(mask.size(), kUnsplit);
  for (size_t i = 0; i < mask.size(); ++i) {
    if (!mask[i]) continue;
    const float z = depth->pixels[i];
    GeometryClass c = GeometryClass::kNone;
    if (z > 0) {
      const double error = std::abs(static_cast<double>(z) - truth->pixels[i]);
      const bool on = error < off_mm;
      if (placed->pixels[i] > 0.5f) {
        c = on ? GeometryClass::kPlacedOn : GeometryClass::kPlacedOff;
      } else {
        c = on ? GeometryClass::kOnMesh : GeometryClass::kOffMesh;
      }
      depth_errors[static_cast<int>(c)].push_back(error);
    }
    classes[i] = static_cast<uint8_t>(c);
  }
  return classes;
}

// The figures of every map split by class.
std::vector<GeometrySplit> SplitByGeometry(const std::vector<Samples>& samples, const int64_t mask[kGeometryClasses],
                                           const std::vector<double> depth_errors[kGeometryClasses]) {
  std::vector<GeometrySplit> out(kGeometryClasses);
  for (int c = 0; c < kGeometryClasses; ++c) {
    out[c].geometry = static_cast<GeometryClass>(c);
    out[c].mask_pixels = mask[c];
    out[c].depth_error_median = Median(depth_errors[c]);
  }
  for (const Samples& map : samples) {
    std::vector<double> errors[kGeometryClasses];
    double total = 0;
    for (size_t i = 0; i < map.error.size(); ++i) {
      total += map.error[i];
      if (map.geometry[i] != kUnsplit) errors[map.geometry[i]].push_back(map.error[i]);
    }
    for (int c = 0; c < kGeometryClasses; ++c) {
      GeometrySplit::Map m;
      m.pixels = static_cast<int64_t>(errors[c].size());
      m.mean = Mean(errors[c]);
      m.median = Median(errors[c]);
      m.share = total > 0 ? m.mean * static_cast<double>(m.pixels) / total : 0;
      out[c].maps.push_back(m);
    }
  }
  return out;
}

}  // namespace

absl::Status EvaluateOptions::Validate() const {
  if (!(band_sigma_px > 0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("evaluate options: band_sigma_px ", band_sigma_px, " is not above 0"));
  }
  if (!(geometry_off_mm > 0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("evaluate options: geometry_off_mm ", geometry_off_mm, " is not above 0"));
  }
  return absl::OkStatus();
}

const char* GeometryClassName(GeometryClass c) {
  switch (c) {
    case GeometryClass::kOnMesh:
      return "on the mesh";
    case GeometryClass::kOffMesh:
      return "on the mesh, off";
    case GeometryClass::kPlacedOn:
      return "placed";
    case GeometryClass::kPlacedOff:
      return "placed, off";
    case GeometryClass::kNone:
      return "no geometry";
  }
  return "?";
}

absl::StatusOr<Evaluation> EvaluatePhotometric(const EvaluateOptions& options) {
  const std::string results =
      options.results_dir.empty() ? options.take_dir + "/derived/photometric" : options.results_dir;
  const std::string truth = options.truth_dir.empty() ? options.take_dir + "/ground_truth" : options.truth_dir;
  if (!fs::is_directory(results)) {
    return absl::NotFoundError(absl::StrCat(results, ": no photometric results (run stage-process photometric)"));
  }
  if (!fs::is_directory(truth)) {
    return absl::NotFoundError(
        absl::StrCat(truth, ": no ground truth (a take on the simulated stage has it unless captured without)"));
  }
  // Units: frame-NNNNNN/<camera> under the results, in order.
  std::set<std::pair<int64_t, std::string>> units;
  const std::regex frame_dir("frame-([0-9]{6})");
  for (const auto& entry : fs::directory_iterator(results)) {
    std::smatch m;
    const std::string name = entry.path().filename().string();
    if (!entry.is_directory() || !std::regex_match(name, m, frame_dir)) continue;
    const int64_t frame = std::stoll(m[1]);
    if (frame < options.first_frame || (options.last_frame >= 0 && frame >= options.last_frame)) continue;
    for (const auto& cam : fs::directory_iterator(entry.path())) {
      const std::string id = cam.path().filename().string();
      if (!options.cameras.empty() &&
          std::find(options.cameras.begin(), options.cameras.end(), id) == options.cameras.end()) {
        continue;
      }
      if (cam.is_directory()) units.emplace(frame, id);
    }
  }
  if (units.empty()) return absl::NotFoundError(absl::StrCat(results, ": no results for these frames and cameras"));
  if (auto s = options.Validate(); !s.ok()) return s;
  // Split by geometry: by that of another run when named, else by these results' own when they had geometry.
  const std::string geometry_from = options.geometry_from.empty() ? results : options.geometry_from;
  const bool split = !options.geometry_from.empty() ||
                     fs::exists(UnitDir(results, units.begin()->first, units.begin()->second) + "/geometry_depth.exr");
  int64_t class_mask[kGeometryClasses] = {};
  std::vector<double> depth_errors[kGeometryClasses];
  struct Map {
    const char* name;
    const char* file;
    const char* truth;
    int kind;
  };
  const Map maps[] = {{"diffuse normal", "diffuse_normal_world.exr", "normal_world.exr", 0},
                      {"specular normal", "specular_normal_world.exr", "normal_world.exr", 0},
                      {"albedo", "albedo.exr", "albedo.exr", 1},
                      {"specular intensity", "specular.exr", "specular.exr", 1},
                      {"roughness", "roughness.exr", "roughness.exr", 2}};
  std::vector<Samples> samples(std::size(maps));
  Evaluation out;
  for (const auto& [frame, camera] : units) {
    const std::string mine = UnitDir(results, frame, camera), theirs = UnitDir(truth, frame, camera);
    auto mask_image = ReadImageFile(theirs + "/mask.png");
    if (!mask_image.ok()) return mask_image.status();
    std::vector<uint8_t> mask(mask_image->pixels.size());
    for (size_t i = 0; i < mask.size(); ++i) mask[i] = mask_image->pixels[i] > 0.99f;  // every ray on the subject
    // Albedo only where the diffuse was solved, specular values only where a lobe was measured: the normal maps say
    // where (zero: not solved).
    auto specular_normal = ReadImageFile(mine + "/specular_normal_world.exr");
    if (!specular_normal.ok()) return specular_normal.status();
    auto diffuse_normal = ReadImageFile(mine + "/diffuse_normal_world.exr");
    if (!diffuse_normal.ok()) return diffuse_normal.status();
    // The solver's flags (flags.png, PhotometricFlag bits): where it says its result is doubtful.
    auto flag_image = ReadImageFile(mine + "/flags.png");
    if (!flag_image.ok()) return flag_image.status();
    std::vector<uint8_t> geometry(mask.size(), kUnsplit);
    if (split) {
      auto classes = ClassifyGeometry(UnitDir(geometry_from, frame, camera), theirs, mask, mask_image->width,
                                      mask_image->height, options.geometry_off_mm, depth_errors);
      if (!classes.ok()) return classes.status();
      geometry = std::move(*classes);
      for (uint8_t c : geometry) {
        if (c != kUnsplit) ++class_mask[c];
      }
    }
    std::vector<uint8_t> doubtful_diffuse(mask.size()), doubtful_specular(mask.size());
    for (size_t i = 0; i < mask.size(); ++i) {
      const auto f = static_cast<uint8_t>(std::lround(flag_image->pixels[i] * 255));
      doubtful_diffuse[i] = (f & (kSaturated | kBadFit | kShadowed | kImplausible)) != 0;
      doubtful_specular[i] = doubtful_diffuse[i] || (f & kSpecularBadFit) != 0;
    }
    for (size_t m = 0; m < std::size(maps); ++m) {
      auto est = ReadImageFile(mine + "/" + maps[m].file);
      if (!est.ok()) return est.status();
      auto gt = ReadImageFile(theirs + "/" + maps[m].truth);
      if (!gt.ok()) return gt.status();
      if (est->width != gt->width || est->height != gt->height || est->channels != gt->channels) {
        return absl::FailedPreconditionError(absl::StrCat(mine, "/", maps[m].file, " is ", est->width, "x", est->height,
                                                          "x", est->channels, ", the truth ", gt->width, "x",
                                                          gt->height, "x", gt->channels));
      }
      if (maps[m].kind != 0) {
        // Not solved: where the normal map says so, and an albedo left out (0: an implausible value).
        const Image& solved = m >= 3 ? *specular_normal : *diffuse_normal;
        const bool albedo = std::string(maps[m].file) == "albedo.exr";
        for (size_t i = 0; i < mask.size(); ++i) {
          if (!Zero(&solved.pixels[3 * i], 3) && !(albedo && Zero(&est->pixels[i * est->channels], est->channels))) {
            continue;
          }
          for (int c = 0; c < est->channels; ++c) est->pixels[i * est->channels + c] = NAN;
        }
      }
      Compare(*est, *gt, mask, m == 1 || m >= 3 ? doubtful_specular : doubtful_diffuse, geometry, maps[m].kind,
              options.band_sigma_px, &samples[m]);
    }
    ++out.units;
  }
  out.mask_pixels = samples[0].mask;
  for (size_t m = 0; m < std::size(maps); ++m) {
    MapError e;
    e.map = maps[m].name;
    e.metric = maps[m].kind == 0 ? "angle (deg)" : maps[m].kind == 1 ? "relative (%)" : "absolute";
    e.pixels = static_cast<int64_t>(samples[m].error.size());
    e.coverage = samples[m].mask > 0 ? static_cast<double>(e.pixels) / static_cast<double>(samples[m].mask) : 0;
    e.mean = Mean(samples[m].error);
    e.median = Median(samples[m].error);
    e.band_mean = Mean(samples[m].band);
    e.band_median = Median(samples[m].band);
    e.band_floor = Mean(samples[m].floor);
    e.confident_pixels = static_cast<int64_t>(samples[m].confident.size());
    e.left_out = e.pixels - e.confident_pixels;
    e.confident_mean = Mean(samples[m].confident);
    e.confident_median = Median(samples[m].confident);
    out.maps.push_back(e);
  }
  if (split) {
    out.geometry_from = geometry_from;
    out.by_geometry = SplitByGeometry(samples, class_mask, depth_errors);
  }
  return out;
}

std::string FormatEvaluation(const Evaluation& e) {
  std::string s = absl::StrFormat(
      "photometric results against ground truth: %d camera frame(s), %d mask pixel(s)\n"
      "%-19s %-13s %9s %8s %8s %8s   %-33s  %s\n",
      e.units, e.mask_pixels, "map", "metric", "pixels", "covered", "mean", "median",
      "pore band: mean (no-detail floor)", "confident: mean, median (left out)");
  for (const MapError& m : e.maps) {
    absl::StrAppend(&s, absl::StrFormat("%-19s %-13s %9d %7.1f%% %8.3f %8.3f   %-33s  %.3f, %.3f (%d)\n", m.map,
                                        m.metric, m.pixels, 100 * m.coverage, m.mean, m.median,
                                        absl::StrFormat("%.3f (%.3f)", m.band_mean, m.band_floor), m.confident_mean,
                                        m.confident_median, m.left_out));
  }
  absl::StrAppend(&s,
                  "confident: pixels not flagged saturated, bad fit, shadowed or implausible (flags.png); left out: "
                  "how many of the compared pixels that excludes\n");
  if (e.by_geometry.empty()) return s;
  absl::StrAppend(&s, "\nby the geometry each pixel was solved with (", e.geometry_from,
                  "): mean, median and share of the map's summed error\n",
                  absl::StrFormat("%-17s %9s %10s", "geometry", "mask px", "|dz| (mm)"));
  for (const MapError& m : e.maps) absl::StrAppend(&s, absl::StrFormat("  %-22s", m.map));
  absl::StrAppend(&s, "\n");
  for (const GeometrySplit& g : e.by_geometry) {
    absl::StrAppend(
        &s, absl::StrFormat("%-17s %9d %10.3f", GeometryClassName(g.geometry), g.mask_pixels, g.depth_error_median));
    for (const GeometrySplit::Map& m : g.maps) {
      absl::StrAppend(&s, absl::StrFormat("  %6.3f %6.3f %6.1f%%   ", m.mean, m.median, 100 * m.share));
    }
    absl::StrAppend(&s, "\n");
  }
  absl::StrAppend(&s,
                  "on the mesh: within the off distance of the truth's surface (camera z); |dz|: the median distance; "
                  "placed: beyond the mesh, at its neighbours' distance or along the solved normals; no geometry: the "
                  "units seen from the stage origin\n");
  return s;
}

std::string EvaluationJson(const Evaluation& e) {
  nlohmann::ordered_json j;
  j["units"] = e.units;
  j["mask_pixels"] = e.mask_pixels;
  j["maps"] = nlohmann::ordered_json::array();
  for (const MapError& m : e.maps) {
    j["maps"].push_back({{"map", m.map},
                         {"metric", m.metric},
                         {"pixels", m.pixels},
                         {"coverage", m.coverage},
                         {"mean", m.mean},
                         {"median", m.median},
                         {"band_mean", m.band_mean},
                         {"band_median", m.band_median},
                         {"band_floor", m.band_floor},
                         {"confident_pixels", m.confident_pixels},
                         {"left_out", m.left_out},
                         {"confident_mean", m.confident_mean},
                         {"confident_median", m.confident_median}});
  }
  if (e.by_geometry.empty()) return j.dump(2);
  j["geometry_from"] = e.geometry_from;
  j["by_geometry"] = nlohmann::ordered_json::array();
  for (const GeometrySplit& g : e.by_geometry) {
    nlohmann::ordered_json maps = nlohmann::ordered_json::array();
    for (size_t m = 0; m < g.maps.size(); ++m) {
      maps.push_back({{"map", e.maps[m].map},
                      {"pixels", g.maps[m].pixels},
                      {"mean", g.maps[m].mean},
                      {"median", g.maps[m].median},
                      {"share", g.maps[m].share}});
    }
    j["by_geometry"].push_back({{"geometry", GeometryClassName(g.geometry)},
                                {"mask_pixels", g.mask_pixels},
                                {"depth_error_median_mm", g.depth_error_median},
                                {"maps", maps}});
  }
  return j.dump(2);
}

}  // namespace stage::processing
