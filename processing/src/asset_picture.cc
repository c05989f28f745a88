// A frame of the asset driven from one camera as a picture (asset_train_internal.h: WriteDrivenPicture).
#include <algorithm>
#include <cmath>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"
#include "asset_train_internal.h"
#include "contact_sheet.h"

namespace stage::processing::asset_internal {
namespace {

constexpr int kTile = 256;
constexpr double kErrorRangeMm = 5;  // the error's colour scale: 0 (dark blue) .. 5 mm (dark red)

// The mesh seen from the front (from +z, orthographically; the square `window` of x and y in mm: centre x, y and
// half side), grey by its (interpolated vertex) normal's slope to a light from the upper left; and where `values`
// (per vertex) is given, the hit's blend of them coloured on the error's scale. Background where no surface is.
void FrontView(const TriangleMesh& mesh, const Eigen::Vector3f& window, const std::vector<float>* values,
               cv::Mat* shaded, cv::Mat* coloured) {
  *shaded = cv::Mat(kTile, kTile, CV_8UC3, cv::Scalar::all(40));
  if (coloured != nullptr) *coloured = shaded->clone();
  const MeshBvh bvh(mesh);
  const std::vector<Eigen::Vector3f> normals = mesh.VertexNormals();
  cv::Mat level(kTile, kTile, CV_8U, cv::Scalar(0)), hits = level.clone();
  const Eigen::Vector3f direction(0, 0, -1);
  const Eigen::Vector3f light = Eigen::Vector3f(-0.4f, 0.5f, 1).normalized();  // from the upper left, before the face
  for (int y = 0; y < kTile; ++y) {
    for (int x = 0; x < kTile; ++x) {
      const float mm_per_pixel = 2 * window.z() / kTile;
      const Eigen::Vector3f origin(window.x() + (x + 0.5f - kTile / 2.0f) * mm_per_pixel,
                                   window.y() - (y + 0.5f - kTile / 2.0f) * mm_per_pixel, 1000);
      MeshHit hit;
      if (!bvh.Nearest(origin, direction, 4000, &hit)) continue;
      const auto& t = mesh.triangles[static_cast<size_t>(hit.triangle)];
      const Eigen::Vector3f n =
          ((1 - hit.b1 - hit.b2) * normals[t[0]] + hit.b1 * normals[t[1]] + hit.b2 * normals[t[2]]).normalized();
      const auto grey = static_cast<uint8_t>(std::clamp(40 + 215 * std::abs(n.dot(light)), 0.0f, 255.0f));
      shaded->at<cv::Vec3b>(y, x) = {grey, grey, grey};
      if (coloured == nullptr) continue;
      const float v = (1 - hit.b1 - hit.b2) * (*values)[t[0]] + hit.b1 * (*values)[t[1]] + hit.b2 * (*values)[t[2]];
      level.at<uint8_t>(y, x) = static_cast<uint8_t>(std::clamp(255 * v / kErrorRangeMm, 0.0, 255.0));
      hits.at<uint8_t>(y, x) = 255;
    }
  }
  if (coloured == nullptr) return;
  cv::Mat colours;
  cv::applyColorMap(level, colours, cv::COLORMAP_TURBO);
  colours.copyTo(*coloured, hits);
}

// The template's vertices on an NCHW map (those the map does not hold stay where the template has them).
TriangleMesh MeshOn(const FaceTemplate& face, const std::vector<float>& map, const std::vector<float>& valid,
                    int size) {
  TriangleMesh mesh = face.mesh;
  for (size_t v = 0; v < mesh.positions.size(); ++v) {
    if (const auto p = SampleNchw(map, valid, size, mesh.uvs[v])) mesh.positions[v] = p->cast<float>();
  }
  return mesh;
}

}  // namespace

absl::Status WriteDrivenPicture(const std::string& path, const DrivenPicture& p) {
  const TriangleMesh truth = MeshOn(*p.face, p.truth, p.valid, p.size);
  const std::vector<float> all(p.valid.size(), 1.f);
  const TriangleMesh driven = MeshOn(*p.face, p.driven, all, p.size);
  std::vector<float> error(truth.positions.size());
  for (size_t v = 0; v < error.size(); ++v) error[v] = (driven.positions[v] - truth.positions[v]).norm();
  // The window: the template's extent in x and y, and a margin.
  Eigen::Vector3f lo = p.face->mesh.positions[0], hi = lo;
  for (const Eigen::Vector3f& q : p.face->mesh.positions) {
    lo = lo.cwiseMin(q);
    hi = hi.cwiseMax(q);
  }
  const Eigen::Vector3f window((lo.x() + hi.x()) / 2, (lo.y() + hi.y()) / 2,
                               0.55f * std::max(hi.x() - lo.x(), hi.y() - lo.y()));
  std::vector<std::pair<std::string, cv::Mat>> tiles(4);
  const cv::Mat crop(p.crop_size, p.crop_size, CV_8U, const_cast<uint8_t*>(p.crop));
  cv::Mat crop_tile;
  cv::resize(crop, crop_tile, {kTile, kTile}, 0, 0, cv::INTER_LINEAR);
  cv::cvtColor(crop_tile, tiles[0].second, cv::COLOR_GRAY2BGR);
  tiles[0].first = p.camera_label;
  FrontView(truth, window, nullptr, &tiles[1].second, nullptr);
  tiles[1].first = "the truth";
  FrontView(driven, window, &error, &tiles[2].second, &tiles[3].second);
  tiles[2].first = "driven from the image";
  tiles[3].first = absl::StrCat("distance to the truth, 0..", kErrorRangeMm, " mm");
  const cv::Mat sheet = ContactSheet(tiles, p.title, /*columns=*/4);
  if (!cv::imwrite(path, sheet)) return absl::UnavailableError(absl::StrCat(path, ": cannot write the picture"));
  return absl::OkStatus();
}

}  // namespace stage::processing::asset_internal
