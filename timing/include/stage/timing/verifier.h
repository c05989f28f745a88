// The schedule verifier: every constraint of a compiled schedule against the rig it came from, each violation with
// the device, the slot, the numbers and what to change (docs/timing.md lists the checks). Errors stop arming;
// warnings are worth knowing.
#pragma once

#include <string>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "stage/timing/pattern_set.h"
#include "stage/v1/rig.pb.h"
#include "stage/v1/timing.pb.h"

namespace stage::timing {

// Names of the checks, as they appear in Violation.check.
inline constexpr absl::string_view kCheckRig = "rig";
inline constexpr absl::string_view kCheckSlotTiming = "slot-timing";
inline constexpr absl::string_view kCheckSteadyLight = "steady-light";
inline constexpr absl::string_view kCheckFrameRate = "frame-rate";
inline constexpr absl::string_view kCheckPatternLock = "pattern-lock";
inline constexpr absl::string_view kCheckTriggerOverlap = "trigger-overlap";
inline constexpr absl::string_view kCheckTriggerLead = "trigger-lead";
inline constexpr absl::string_view kCheckLinkBandwidth = "link-bandwidth";
inline constexpr absl::string_view kCheckCameraRam = "camera-ram";
inline constexpr absl::string_view kCheckDiskWrite = "disk-write";
inline constexpr absl::string_view kCheckLedDuty = "led-duty";
inline constexpr absl::string_view kCheckLedThermal = "led-thermal";
inline constexpr absl::string_view kCheckFlicker = "flicker";

// Usable payload of a camera link, bytes/s of Ethernet line rate (GigE kinds) or of net payload (USB3, CoaXPress);
// 0 for on-camera RAM.
double LinkBudgetBytesPerSecond(v1::LinkKind link);
// Bytes on the wire for one frame over GigE Vision: GVSP payload packets of `packet_size` bytes (IP packet incl. IP,
// UDP and GVSP headers) plus Ethernet framing, preamble and inter-frame gap, plus leader and trailer.
double GigeWireBytesPerFrame(double frame_bytes, uint32_t packet_size);

// Runs every check. `rig` has had its defaults applied and passed validation; `schedule` was compiled from it and
// `patterns`. The report carries the schedule. A fix that proposes a setting (a divider, a frame rate) is offered only
// after the checks, run again with that setting, find the violation gone and no new error.
v1::TimingReport VerifySchedule(const v1::RigConfig& rig, const PatternSet& patterns, const v1::Schedule& schedule);

// Loads the rig's pattern set (relative to `base_dir`), compiles and verifies.
absl::StatusOr<v1::TimingReport> CheckRigTiming(const v1::RigConfig& rig, absl::string_view base_dir);

// "error" / "warning".
absl::string_view SeverityName(v1::Severity severity);

}  // namespace stage::timing
