// Words for the processing stages: see processing_names.h.
#include "stage/common/processing_names.h"

#include <string>

#include "absl/strings/ascii.h"
#include "absl/strings/str_replace.h"

namespace stage {

std::optional<v1::ProcessingStage> ParseProcessingStage(absl::string_view word) {
  std::string name = absl::AsciiStrToUpper(word == "calibrate" ? "calibration" : word);
  absl::StrReplaceAll({{"-", "_"}}, &name);
  v1::ProcessingStage stage;
  if (!v1::ProcessingStage_Parse("PROCESSING_STAGE_" + name, &stage) || stage == v1::PROCESSING_STAGE_UNSPECIFIED) {
    return std::nullopt;
  }
  return stage;
}

}  // namespace stage
