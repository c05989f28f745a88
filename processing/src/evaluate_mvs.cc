// Multi-view stereo's meshes against the ground truth: see evaluate_mvs.h.
#include "stage/processing/evaluate_mvs.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <nanoflann.hpp>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "stage/common/camera_calibration.h"
#include "stage/common/file_util.h"
#include "stage/common/status.h"
#include "stage/processing/calibrate.h"
#include "stage/processing/map_files.h"
#include "stage/processing/photometric_stage.h"
#include "statistics.h"

namespace stage::processing {
namespace {

namespace fs = std::filesystem;
constexpr double kPi = 3.14159265358979323846;

// The point of triangle (a, b, c) nearest p (Ericson, Real-Time Collision Detection, 5.1.5).
Eigen::Vector3f ClosestOnTriangle(const Eigen::Vector3f& p, const Eigen::Vector3f& a, const Eigen::Vector3f& b,
                                  const Eigen::Vector3f& c) {
  const Eigen::Vector3f ab = b - a, ac = c - a, ap = p - a;
  const float d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0 && d2 <= 0) return a;
  const Eigen::Vector3f bp = p - b;
  const float d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0 && d4 <= d3) return b;
  const float vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) return a + d1 / (d1 - d3) * ab;
  const Eigen::Vector3f cp = p - c;
  const float d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0 && d5 <= d6) return c;
  const float vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) return a + d2 / (d2 - d6) * ac;
  const float va = d3 * d6 - d5 * d4;
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) return b + (d4 - d3) / ((d4 - d3) + (d5 - d6)) * (c - b);
  const float denom = 1 / (va + vb + vc);
  return a + ab * (vb * denom) + ac * (vc * denom);
}

// The region of a true triangle: the eyes are their own part; the mouth, the face and the rest of the skin are where
// the procedural head's UV layout puts them (sim/src/head.cc: theta, the angle round the head from the front, is
// u 2 pi - pi; phi, the elevation, v pi - pi / 2): the mouth about theta 0, phi -0.485 (lips and opening); the face
// within 75 degrees of the front, from 40 degrees below the head's centre to 35 above (chin to forehead).
HeadRegion RegionOf(const TriangleMesh& m, size_t t) {
  if (!m.parts.empty() && m.parts[t] == 1) return HeadRegion::kEyes;
  if (m.uvs.size() != m.positions.size()) return HeadRegion::kFace;
  const auto& tri = m.triangles[t];
  const Eigen::Vector2f uv = (m.uvs[tri[0]] + m.uvs[tri[1]] + m.uvs[tri[2]]) / 3;
  const double th = uv.x() * 2 * kPi - kPi, ph = uv.y() * kPi - kPi / 2;
  if (std::abs(th) < 0.3 && std::abs(ph + 0.485) < 0.07) return HeadRegion::kMouth;
  const double deg = 180 / kPi;
  return std::abs(th) * deg <= 75 && ph * deg >= -40 && ph * deg <= 35 ? HeadRegion::kFace : HeadRegion::kOtherSkin;
}

// Which true triangles at least `min_cameras` of `cameras` see: at less than max_angle_deg from the triangle's normal
// (either side: the winding is not relied on; the head is closed, so a triangle facing away is hidden by the near
// side), in the camera's image, unoccluded.
std::vector<char> SeenTriangles(const MeshBvh& bvh, const std::vector<CameraModel>& cameras, int min_cameras,
                                double max_angle_deg) {
  const float min_cos = static_cast<float>(std::cos(max_angle_deg * kPi / 180));
  const TriangleMesh& m = bvh.mesh();
  std::vector<char> seen(m.triangles.size(), 0);
  for (size_t t = 0; t < m.triangles.size(); ++t) {
    const auto& tri = m.triangles[t];
    const Eigen::Vector3f a = m.positions[tri[0]], b = m.positions[tri[1]], c = m.positions[tri[2]];
    const Eigen::Vector3f centre = (a + b + c) / 3;
    const Eigen::Vector3f normal = (b - a).cross(c - a).normalized();
    int count = 0;
    for (const CameraModel& cam : cameras) {
      const Eigen::Vector3f eye = cam.position().cast<float>();
      if (std::abs(normal.dot((eye - centre).normalized())) < min_cos) continue;
      Eigen::Vector2d px;
      if (!cam.Project(centre.cast<double>(), &px) || px.x() < 0 || px.y() < 0 || px.x() > cam.width() - 1 ||
          px.y() > cam.height() - 1) {
        continue;
      }
      if (bvh.Occluded(centre + 0.05f * (eye - centre).normalized(), eye)) continue;
      if (++count >= min_cameras) break;
    }
    seen[t] = count >= min_cameras;
  }
  return seen;
}

double TriangleArea(const TriangleMesh& m, size_t t) {
  const auto& tri = m.triangles[t];
  return 0.5 * (m.positions[tri[1]] - m.positions[tri[0]]).cross(m.positions[tri[2]] - m.positions[tri[0]]).norm();
}

// The views' depth maps against the truth's, where both have a depth: signed differences, mm.
absl::Status CompareDepthMaps(const std::string& results_frame, const std::string& truth_frame,
                              std::vector<double>* differences) {
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(results_frame + "/depth", ec)) {
    if (entry.path().extension() != ".exr") continue;
    const std::string camera = entry.path().stem().string();
    STAGE_ASSIGN_OR_RETURN(const Image got, ReadImageFile(entry.path().string()));
    STAGE_ASSIGN_OR_RETURN(const Image want, ReadImageFile(truth_frame + "/" + camera + "/depth.exr"));
    if (got.width != want.width || got.height != want.height) {
      return absl::FailedPreconditionError(absl::StrCat(entry.path().string(), ": ", got.width, "x", got.height,
                                                        ", the truth's ", want.width, "x", want.height,
                                                        " (compare at --image-scale 1)"));
    }
    for (size_t i = 0; i < static_cast<size_t>(got.width) * got.height; ++i) {
      const float g = got.pixels[i * got.channels], w = want.pixels[i * want.channels];
      if (g > 0 && w > 0) differences->push_back(g - w);
    }
  }
  return absl::OkStatus();
}

struct RegionSums {
  std::vector<double> distances;
  double seen_area = 0, within_area = 0, covered_area = 0;
  double surface_sq = 0, surface_area = 0;  // squared distances of the mesh's triangle centres, area-weighted
};

// Whether the line along the true surface's normal at `centre` meets the reconstruction within +-reach: the surface
// is there, not a hole beside which the nearest reconstructed point lies.
bool Covered(const MeshBvh& recon, const Eigen::Vector3f& centre, const Eigen::Vector3f& normal, float reach) {
  MeshHit hit;
  return recon.Nearest(centre - reach * normal, normal, 2 * reach, &hit);
}

// One frame's sums per region.
void EvaluateFrame(const TriangleMesh& truth, const TriangleMesh& recon, const std::vector<CameraModel>& cameras,
                   const MvsEvaluateOptions& o, RegionSums sums[kHeadRegions], MvsEvaluation* e) {
  MeshBvh bvh(truth);
  const std::vector<char> seen = SeenTriangles(bvh, cameras, o.min_cameras, o.max_view_angle_deg);
  const SurfaceDistance to_truth(truth);
  for (const Eigen::Vector3f& v : recon.positions) {
    int32_t t = -1;
    const float d = to_truth.Distance(v, &t);
    ++e->vertices;
    if (t < 0 || !seen[t]) {
      ++e->unseen_vertices;
      continue;
    }
    sums[static_cast<int>(RegionOf(truth, t))].distances.push_back(d);
  }
  // The surface as well as its vertices: a hole's patch (MvsOptions::fill_holes_mm) adds triangles, not vertices.
  for (size_t k = 0; k < recon.triangles.size(); ++k) {
    const auto& tri = recon.triangles[k];
    int32_t t = -1;
    const float d =
        to_truth.Distance((recon.positions[tri[0]] + recon.positions[tri[1]] + recon.positions[tri[2]]) / 3, &t);
    if (t < 0 || !seen[t]) continue;
    RegionSums& r = sums[static_cast<int>(RegionOf(truth, t))];
    const double area = TriangleArea(recon, k);
    r.surface_sq += area * d * d;
    r.surface_area += area;
  }
  const SurfaceDistance to_recon(recon);
  const MeshBvh recon_bvh(recon);
  for (size_t t = 0; t < truth.triangles.size(); ++t) {
    if (!seen[t]) continue;
    const auto& tri = truth.triangles[t];
    const Eigen::Vector3f a = truth.positions[tri[0]], b = truth.positions[tri[1]], c = truth.positions[tri[2]];
    const Eigen::Vector3f centre = (a + b + c) / 3;
    const double area = TriangleArea(truth, t);
    RegionSums& s = sums[static_cast<int>(RegionOf(truth, t))];
    s.seen_area += area;
    if (recon.triangles.empty()) continue;
    if (to_recon.Distance(centre) <= o.within_mm) s.within_area += area;
    if (Covered(recon_bvh, centre, (b - a).cross(c - a).normalized(), static_cast<float>(o.within_mm))) {
      s.covered_area += area;
    }
  }
}

}  // namespace

// The triangles' centres in a k-d tree (nanoflann).
struct SurfaceDistance::Index {
  std::vector<Eigen::Vector3f> centres;
  size_t kdtree_get_point_count() const { return centres.size(); }
  float kdtree_get_pt(size_t i, size_t dim) const { return centres[i][static_cast<int>(dim)]; }
  template <class Box>
  bool kdtree_get_bbox(Box&) const {
    return false;
  }
  using Tree = nanoflann::KDTreeSingleIndexAdaptor<nanoflann::L2_Simple_Adaptor<float, Index>, Index, 3>;
  std::unique_ptr<Tree> tree;
};

SurfaceDistance::SurfaceDistance(const TriangleMesh& mesh) : mesh_(mesh), index_(new Index) {
  for (const auto& tri : mesh.triangles) {
    index_->centres.push_back((mesh.positions[tri[0]] + mesh.positions[tri[1]] + mesh.positions[tri[2]]) / 3);
  }
  index_->tree = std::make_unique<Index::Tree>(3, *index_, nanoflann::KDTreeSingleIndexAdaptorParams(10));
  if (!index_->centres.empty()) index_->tree->buildIndex();
}

SurfaceDistance::~SurfaceDistance() { delete index_; }

float SurfaceDistance::Distance(const Eigen::Vector3f& p, int32_t* triangle) const {
  if (index_->centres.empty()) {
    if (triangle != nullptr) *triangle = -1;
    return std::numeric_limits<float>::infinity();
  }
  return (Closest(p, triangle) - p).norm();
}

Eigen::Vector3f SurfaceDistance::Closest(const Eigen::Vector3f& p, int32_t* triangle) const {
  if (triangle != nullptr) *triangle = -1;
  if (index_->centres.empty()) return p;
  constexpr size_t kCandidates = 16;
  uint32_t ids[kCandidates];
  float d2[kCandidates];
  const size_t found = index_->tree->knnSearch(p.data(), kCandidates, ids, d2);
  float best = std::numeric_limits<float>::infinity();
  Eigen::Vector3f closest = p;
  for (size_t i = 0; i < found; ++i) {
    const auto& tri = mesh_.triangles[ids[i]];
    const Eigen::Vector3f q =
        ClosestOnTriangle(p, mesh_.positions[tri[0]], mesh_.positions[tri[1]], mesh_.positions[tri[2]]);
    const float d = (q - p).squaredNorm();
    if (d < best) {
      best = d;
      closest = q;
      if (triangle != nullptr) *triangle = static_cast<int32_t>(ids[i]);
    }
  }
  return closest;
}

const char* HeadRegionName(HeadRegion r) {
  switch (r) {
    case HeadRegion::kFace:
      return "face";
    case HeadRegion::kEyes:
      return "eyes";
    case HeadRegion::kMouth:
      return "mouth";
    case HeadRegion::kOtherSkin:
      return "other skin";
  }
  return "?";
}

absl::Status MvsEvaluateOptions::Validate() const {
  if (take_dir.empty()) return absl::InvalidArgumentError("evaluate mvs: no take directory");
  if (!(within_mm > 0)) return absl::InvalidArgumentError(absl::StrCat("evaluate mvs: within_mm ", within_mm, " <= 0"));
  if (min_cameras < 1)
    return absl::InvalidArgumentError(absl::StrCat("evaluate mvs: min_cameras ", min_cameras, " < 1"));
  return absl::OkStatus();
}

// The calibration an MVS run placed its cameras with (its run.json), against the truth's cameras.
absl::StatusOr<TruthComparison> RunFrameToTruth(const std::string& take_dir, const std::string& results,
                                                const CameraCalibration& truth, std::string* placed_by) {
  const std::string path = results + "/run.json";
  STAGE_ASSIGN_OR_RETURN(const std::string text, ReadFileToString(path, "the multi-view stereo run's record"));
  const nlohmann::json run = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (run.is_discarded() || !run.contains("calibration") || !run["calibration"].is_string()) {
    return absl::InvalidArgumentError(absl::StrCat(path,
                                                   ": no \"calibration\" string (written before evaluation "
                                                   "could take a calibration's frame out; run mvs again)"));
  }
  const std::string spec = run["calibration"].get<std::string>();
  if (placed_by != nullptr) *placed_by = run.value("cameras_placed_by", spec);
  std::optional<CameraCalibration> placed;
  if (spec.empty()) {
    STAGE_ASSIGN_OR_RETURN(const LoadedRig rig, LoadTakeRig(take_dir));
    STAGE_ASSIGN_OR_RETURN(placed, NominalCalibration(rig));
  } else {
    STAGE_ASSIGN_OR_RETURN(placed, LoadJobCalibration(take_dir, spec));
  }
  auto compared = CompareCalibrations(*placed, truth);
  if (!compared.ok())
    return absl::Status(compared.status().code(), absl::StrCat(path, ": ", compared.status().message()));
  return compared;
}

// `mesh` moved by `t`.
void Move(const Eigen::Isometry3d& t, TriangleMesh* mesh) {
  const Eigen::Isometry3f tf = t.cast<float>();
  for (Eigen::Vector3f& p : mesh->positions) p = tf * p;
}

absl::StatusOr<MvsEvaluation> EvaluateMvs(const MvsEvaluateOptions& o) {
  STAGE_RETURN_IF_ERROR(o.Validate());
  const std::string results = o.results_dir.empty() ? o.take_dir + "/derived/mvs" : o.results_dir;
  const std::string truth = o.truth_dir.empty() ? o.take_dir + "/ground_truth" : o.truth_dir;
  STAGE_ASSIGN_OR_RETURN(const LoadedRig rig, LoadTakeRig(o.take_dir));
  STAGE_ASSIGN_OR_RETURN(const CameraCalibration placed, ReadCameraCalibration(truth + "/cameras.json"));
  std::vector<CameraModel> cameras;
  for (const v1::CameraConfig& c : rig.rig.cameras()) {
    if (c.role() != v1::CAMERA_ROLE_MACHINE_VISION) continue;
    const CameraModel* m = placed.Find(c.id());
    if (m == nullptr) return absl::NotFoundError(absl::StrCat(truth, "/cameras.json: no camera \"", c.id(), "\""));
    cameras.push_back(*m);
  }
  MvsEvaluation e;
  e.within_mm = o.within_mm;
  STAGE_ASSIGN_OR_RETURN(const TruthComparison in_truth,
                         RunFrameToTruth(o.take_dir, results, placed, &e.cameras_placed_by));
  e.frame_offset_mm = in_truth.frame_offset_mm;
  e.frame_rotation_deg = in_truth.frame_rotation_deg;
  RegionSums sums[kHeadRegions];
  std::vector<double> depth_differences;
  for (int64_t frame = o.first_frame; o.last_frame < 0 || frame < o.last_frame; ++frame) {
    const std::string recon_path = absl::StrFormat("%s/frame-%06d/mesh.obj", results, frame);
    if (!fs::exists(recon_path)) {
      if (o.last_frame < 0 && e.frames > 0) break;
      return absl::NotFoundError(absl::StrCat(recon_path, ": no reconstruction of frame ", frame));
    }
    STAGE_ASSIGN_OR_RETURN(TriangleMesh recon, ReadObj(recon_path));
    Move(in_truth.to_truth, &recon);
    STAGE_ASSIGN_OR_RETURN(const TriangleMesh true_mesh,
                           ReadObj(absl::StrFormat("%s/frame-%06d/mesh.obj", truth, frame)));
    EvaluateFrame(true_mesh, recon, cameras, o, sums, &e);
    STAGE_RETURN_IF_ERROR(CompareDepthMaps(absl::StrFormat("%s/frame-%06d", results, frame),
                                           absl::StrFormat("%s/frame-%06d", truth, frame), &depth_differences));
    ++e.frames;
  }
  e.depth_pixels = static_cast<int64_t>(depth_differences.size());
  if (!depth_differences.empty()) {
    e.depth_median_mm = Median(depth_differences);
    for (double& d : depth_differences) d = std::abs(d);
    e.depth_median_abs_mm = Median(depth_differences);
  }
  for (int r = 0; r < kHeadRegions; ++r) {
    MvsRegionError out;
    out.region = static_cast<HeadRegion>(r);
    std::vector<double>& d = sums[r].distances;
    out.vertices = static_cast<int64_t>(d.size());
    if (!d.empty()) {
      double sq = 0;
      for (double x : d) sq += x * x;
      out.rmse_mm = std::sqrt(sq / static_cast<double>(d.size()));
      out.median_mm = Median(d);
      out.p95_mm = Quantile(d, 95, 100);
    }
    out.seen_area_mm2 = sums[r].seen_area;
    out.completeness = sums[r].seen_area > 0 ? sums[r].within_area / sums[r].seen_area : 0;
    out.coverage = sums[r].seen_area > 0 ? sums[r].covered_area / sums[r].seen_area : 0;
    out.surface_rmse_mm = sums[r].surface_area > 0 ? std::sqrt(sums[r].surface_sq / sums[r].surface_area) : 0;
    e.regions.push_back(out);
  }
  return e;
}

absl::Status WriteMvsPictures(const std::string& take_dir, const std::string& results_dir, int64_t frame,
                              const std::string& camera, const std::string& out_prefix, double error_range_mm) {
  const std::string results = results_dir.empty() ? take_dir + "/derived/mvs" : results_dir;
  STAGE_ASSIGN_OR_RETURN(TriangleMesh recon, ReadObj(absl::StrFormat("%s/frame-%06d/mesh.obj", results, frame)));
  STAGE_ASSIGN_OR_RETURN(const TriangleMesh truth,
                         ReadObj(absl::StrFormat("%s/ground_truth/frame-%06d/mesh.obj", take_dir, frame)));
  STAGE_ASSIGN_OR_RETURN(const CameraCalibration placed,
                         ReadCameraCalibration(take_dir + "/ground_truth/cameras.json"));
  STAGE_ASSIGN_OR_RETURN(const TruthComparison in_truth, RunFrameToTruth(take_dir, results, placed));
  Move(in_truth.to_truth, &recon);
  const CameraModel* sensor = placed.Find(camera);
  if (sensor == nullptr) return absl::NotFoundError(absl::StrCat("no camera \"", camera, "\" in the ground truth"));
  // The camera at a picture's size: 1024 pixels wide at most.
  const CameraModel cam = sensor->Scaled(std::min(1.0, 1024.0 / sensor->width()));
  const MeshBvh bvh(std::move(recon));
  const SurfaceDistance to_truth(truth);
  const std::vector<Eigen::Vector3f> rays = cam.PixelRays();
  const Eigen::Vector3f origin = cam.position().cast<float>();
  cv::Mat shaded(cam.height(), cam.width(), CV_8UC3, cv::Scalar(40, 40, 40)), error = shaded.clone();
  for (int y = 0; y < cam.height(); ++y) {
    for (int x = 0; x < cam.width(); ++x) {
      const Eigen::Vector3f& d = rays[static_cast<size_t>(y) * cam.width() + x];
      MeshHit hit;
      if (!bvh.Nearest(origin, d, INFINITY, &hit)) continue;
      const auto& t = bvh.mesh().triangles[static_cast<size_t>(hit.triangle)];
      const auto& p = bvh.mesh().positions;
      const Eigen::Vector3f n = (p[t[1]] - p[t[0]]).cross(p[t[2]] - p[t[0]]).normalized();
      const auto v = static_cast<uint8_t>(std::clamp(40 + 215 * std::abs(n.dot(d)), 0.0f, 255.0f));
      shaded.at<cv::Vec3b>(y, x) = {v, v, v};
      const double e = to_truth.Distance(origin + hit.t * d);
      cv::Mat one(1, 1, CV_8U, cv::Scalar(std::clamp(255 * e / error_range_mm, 0.0, 255.0))), colour;
      cv::applyColorMap(one, colour, cv::COLORMAP_TURBO);
      error.at<cv::Vec3b>(y, x) = colour.at<cv::Vec3b>(0, 0);
    }
  }
  if (!cv::imwrite(out_prefix + "-mesh.png", shaded) || !cv::imwrite(out_prefix + "-error.png", error)) {
    return absl::UnavailableError(absl::StrCat(out_prefix, "-{mesh,error}.png: cannot write"));
  }
  return absl::OkStatus();
}

std::string FormatMvsEvaluation(const MvsEvaluation& e) {
  std::string out = absl::StrFormat(
      "multi-view stereo against the truth: %d frame(s), %d vertices (%d nearest to surface no two cameras see)\n",
      e.frames, e.vertices, e.unseen_vertices);
  absl::StrAppendFormat(&out, "(cameras placed by %s; its frame moved onto the truth's by %.3f mm, %.4f deg)\n",
                        e.cameras_placed_by, e.frame_offset_mm, e.frame_rotation_deg);
  absl::StrAppendFormat(&out, "%-10s %9s %9s %10s %8s %12s %12s %14s %9s\n", "region", "vertices", "RMSE mm",
                        "median mm", "p95 mm", "surface RMSE", "seen mm^2",
                        absl::StrFormat("within %.2g mm", e.within_mm), "covered");
  for (const MvsRegionError& r : e.regions) {
    absl::StrAppendFormat(&out, "%-10s %9d %9.3f %10.3f %8.3f %12.3f %12.0f %13.1f%% %8.1f%%\n",
                          HeadRegionName(r.region), r.vertices, r.rmse_mm, r.median_mm, r.p95_mm, r.surface_rmse_mm,
                          r.seen_area_mm2, 100 * r.completeness, 100 * r.coverage);
  }
  absl::StrAppendFormat(&out,
                        "(surface RMSE: of the mesh's triangle centres, weighted by area; covered: the true surface's "
                        "normal meets the mesh within %.2g mm, the rest is holes)\n",
                        e.within_mm);
  absl::StrAppendFormat(&out,
                        "depth maps: %d pixels with a depth and a true one; median error %+.3f mm, median "
                        "absolute %.3f mm\n",
                        e.depth_pixels, e.depth_median_mm, e.depth_median_abs_mm);
  return out;
}

std::string MvsEvaluationJson(const MvsEvaluation& e) {
  nlohmann::ordered_json j;
  j["frames"] = e.frames;
  j["vertices"] = e.vertices;
  j["unseen_vertices"] = e.unseen_vertices;
  j["within_mm"] = e.within_mm;
  j["cameras_placed_by"] = e.cameras_placed_by;
  j["frame_to_truth"] = {{"offset_mm", e.frame_offset_mm}, {"rotation_deg", e.frame_rotation_deg}};
  j["depth_maps"] = {
      {"pixels", e.depth_pixels}, {"median_mm", e.depth_median_mm}, {"median_abs_mm", e.depth_median_abs_mm}};
  for (const MvsRegionError& r : e.regions) {
    j["regions"][HeadRegionName(r.region)] = {
        {"vertices", r.vertices},           {"rmse_mm", r.rmse_mm},
        {"median_mm", r.median_mm},         {"p95_mm", r.p95_mm},
        {"seen_area_mm2", r.seen_area_mm2}, {"completeness", r.completeness},
        {"coverage", r.coverage},           {"surface_rmse_mm", r.surface_rmse_mm}};
  }
  return j.dump();
}

}  // namespace stage::processing
