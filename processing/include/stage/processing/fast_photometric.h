// Photometric stereo without geometry, fast enough for a full 4096x2304 camera set (docs/processing.md#speed): the
// model of SolvePhotometric without geometry (every unit seen from the stage origin), with every sum over the units
// looked up in tables built once per camera, the specular lobe found from its moments instead of fitted, and the
// demosaicing folded into the solve (each pattern's channel sum from its 3 x 3 neighbourhood of the raw mosaic; the
// albedo solved per pixel in the colour the pixel measures, then demosaiced).
#pragma once

#include <memory>

#include "absl/status/statusor.h"
#include "stage/processing/light_model.h"
#include "stage/processing/photometric.h"
#include "stage/processing/take_frames.h"

namespace stage::processing {

// What the fast solver looks up instead of summing over the units per pixel, built once per camera (its view and
// noise model) and used for every frame:
// - diffuse, on an octahedral map of normals: H_p(n) of every cross pattern, the noise-weighted least-squares solution
//   operator u = M(n) d, and the sum of H_p over the patterns (for albedo);
// - specular, on an octahedral map of the lobe's measured mean direction and a range of roughness: the way from that
//   direction to the true mirror direction (the dome's discrete units pull the mean towards them), the lobe's angular
//   variance and total, and its image under every pattern (to take it away from the diffuse).
class PhotometricTables {
 public:
  struct Data;
  static absl::StatusOr<std::shared_ptr<const PhotometricTables>> Build(const LightModel& light,
                                                                        const PhotometricCamera& camera,
                                                                        const PhotometricOptions& options = {});
  ~PhotometricTables();
  const Data& data() const { return *data_; }

 private:
  PhotometricTables() = default;
  std::unique_ptr<Data> data_;
};

// One camera's cycle (raw, as recorded) solved with `tables` (built for this camera). InvalidArgument names a size
// mismatch or a flat field of another size.
absl::StatusOr<PhotometricMaps> SolvePhotometricFast(const LightModel& light, const PhotometricTables& tables,
                                                     const CycleFrames& cycle, const RawCorrection& correction,
                                                     const PhotometricCamera& camera,
                                                     const PhotometricOptions& options = {});
// The same into `maps`, whose memory is reused when it already has this size (a take's frames one after another).
absl::Status SolvePhotometricFast(const LightModel& light, const PhotometricTables& tables, const CycleFrames& cycle,
                                  const RawCorrection& correction, const PhotometricCamera& camera,
                                  const PhotometricOptions& options, PhotometricMaps* maps);

}  // namespace stage::processing
