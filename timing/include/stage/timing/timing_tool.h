// What `stagectl timing` (on a rig file) and the controller's timing RPCs (on the live rig) share: verification with
// what-if overrides, waveform export, and the text a hardware engineer reads.
#pragma once

#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "stage/common/rig.h"
#include "stage/v1/timing.pb.h"

namespace stage::timing {

// Most slots one export may cover (about 110 s at 912 Hz).
inline constexpr int64_t kMaxExportSlots = 100'000;

// Applies `query.overrides` to `rig` (ApplyRigOverrides), then loads the pattern set, compiles and verifies.
// InvalidArgument names a bad override or the field it makes invalid.
absl::StatusOr<v1::TimingReport> CheckTiming(const LoadedRig& rig, const v1::TimingQuery& query);

// CheckTiming, then the requested files over the requested window.
absl::StatusOr<v1::TimingExport> ExportTiming(const LoadedRig& rig, const v1::TimingExportRequest& request);

// Every violation with its fix, then a one-line verdict ("0 errors, 1 warning: the schedule may be armed").
std::string FormatViolations(const v1::TimingReport& report, absl::string_view rig_name);

// Per device: the light nodes' switching and steady windows, each camera's trigger, exposure, readout, slack and
// load, flicker components and recording hosts.
std::string FormatScheduleSummary(const v1::TimingReport& report, absl::string_view rig_name);

}  // namespace stage::timing
