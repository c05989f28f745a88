// Photometric maps on disk (docs/processing.md#outputs): per frame and camera, float OpenEXR maps (normals in the
// stage and camera frames, albedo, specular intensity, roughness, confidence), the flags as PNG, 8-bit PNG previews,
// metrics.json, and a contact sheet of the previews for people to look at. The same files are read back for
// evaluation.
#pragma once

#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "stage/processing/photometric.h"

namespace stage::processing {

// Writes `maps` into `dir` (created). `metrics_json`: the unit's metrics, written as metrics.json. `title`: the
// contact sheet's caption.
absl::Status WriteMapFiles(const std::string& dir, const PhotometricMaps& maps, const std::string& metrics_json,
                           const std::string& title);

// The geometry a unit was solved with (docs/processing.md#outputs), for evaluation to split its figures by: into
// `dir` (created), geometry_depth.exr (per pixel, the camera-frame z in mm of the point it was solved at, as the ground
// truth's depth.exr; 0: none) and geometry_placed.png (255 where FillGeometry placed that point beyond the mesh, else
// 0).
absl::Status WriteGeometryFiles(const std::string& dir, const PixelGeometry& geometry, const PhotometricCamera& camera);

// Fused UV textures into `dir` (created): every image of `exr` as NAME.exr, and for albedo, normal_tangent, specular
// and roughness an 8-bit NAME.png preview, all of them on contact_sheet.png under `title`; `metrics_json` as
// metrics.json.
absl::Status WriteTextureFiles(const std::string& dir, const std::vector<std::pair<std::string, const Image*>>& exr,
                               const std::string& metrics_json, const std::string& title);

// Reads a float image (OpenEXR, 1, 3 or 4 channels; values in x, y, z / R, G, B(, A) order) or an 8/16-bit PNG.
absl::StatusOr<Image> ReadImageFile(const std::string& path);

// Writes a float image (1, 3 or 4 channels: R, G, B, A) as float32 OpenEXR.
absl::Status WriteExr(const std::string& path, const Image& image);

}  // namespace stage::processing
