// Words for the take.proto enums: see take_names.h.
#include "stage/common/take_names.h"

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/string_view.h"

namespace stage {
namespace {

std::string After(const std::string& name, absl::string_view prefix) {
  return absl::StartsWith(name, prefix) ? name.substr(prefix.size()) : name;
}

}  // namespace

std::string SessionStateName(v1::SessionState state) {
  return absl::AsciiStrToLower(After(v1::SessionState_Name(state), "SESSION_STATE_"));
}

std::string TakeOutcomeName(v1::TakeOutcome outcome) {
  return outcome == v1::TAKE_OUTCOME_UNSPECIFIED ? "" : After(v1::TakeOutcome_Name(outcome), "TAKE_OUTCOME_");
}

std::string CapturePhaseName(v1::CapturePhase phase) {
  return absl::AsciiStrToLower(After(v1::CapturePhase_Name(phase), "CAPTURE_PHASE_"));
}

std::string TakeStateName(v1::TakeState state) {
  return absl::AsciiStrToLower(After(v1::TakeState_Name(state), "TAKE_STATE_"));
}

std::string LossReasonName(v1::LossReason reason) {
  std::string words = absl::AsciiStrToLower(After(v1::LossReason_Name(reason), "LOSS_REASON_"));
  for (char& c : words) c = c == '_' ? ' ' : c;
  return words.empty() ? "unknown" : words;
}

}  // namespace stage
