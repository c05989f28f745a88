// Words for the processing stages (processing_worker.proto's ProcessingStage), as command lines and the processing
// graph's files name them: "mvs", "asset-train", "calibration" (or "calibrate", stage-process run's word).
#pragma once

#include <optional>

#include "absl/strings/string_view.h"
#include "stage/v1/processing_worker.pb.h"

namespace stage {

// "mvs" -> PROCESSING_STAGE_MVS, "asset-train" -> PROCESSING_STAGE_ASSET_TRAIN; nullopt for a word that names none.
std::optional<v1::ProcessingStage> ParseProcessingStage(absl::string_view word);

}  // namespace stage
