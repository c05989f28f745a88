// Loading the rig configuration: YAML -> stage.v1.RigConfig, documented defaults, then semantic validation whose
// errors name the file, the line and the field path ("fastage.yaml:42:7: cameras[3].exposure_us: 0 is not > 0").
#pragma once

#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "stage/common/yaml_proto.h"
#include "stage/v1/rig.pb.h"

namespace stage {

// The name by which the shipped default rig is loaded in place of a file.
inline constexpr absl::string_view kBuiltinRigName = "builtin:fastage";

struct RigValidationOptions {
  // Require every node to have an `address` (stage-controller needs them; stage-sim assigns them itself).
  bool require_addresses = false;
};

struct LoadedRig {
  v1::RigConfig rig;
  // The file as named in messages ("rigs/fastage.yaml", or "fastage.yaml (built in)").
  std::string source_name;
  // Directory that relative paths in the rig are resolved against.
  std::string base_dir;
  SourceMap source_map;
  // The rig as its file wrote it, before the defaults (unset where the rig did not come from LoadRig): overrides apply
  // to it, and the defaults that follow other fields follow them (a slot rate set with --set moves the frame rates
  // that default to it).
  std::optional<v1::RigConfig> as_written;
};

// Loads, fills defaults and validates. `path` is a YAML (or JSON) file, or kBuiltinRigName. On a validation failure
// the status message is the first error followed by "(and N more errors)" when there are more; `all_errors`, if not
// null, receives every error, one per entry.
absl::StatusOr<LoadedRig> LoadRig(absl::string_view path, const RigValidationOptions& options = {},
                                  std::vector<std::string>* all_errors = nullptr);

// As LoadRig, from text. `source_name` is used in messages only.
absl::StatusOr<LoadedRig> LoadRigFromText(absl::string_view text, absl::string_view source_name,
                                          absl::string_view base_dir, const RigValidationOptions& options = {},
                                          std::vector<std::string>* all_errors = nullptr);

// Fills every documented default that `rig` leaves unset (see rig.proto). Idempotent.
void ApplyRigDefaults(v1::RigConfig* rig);

// Every semantic error of a rig that has had its defaults applied, each as "<path>: <message>" paired with the path
// so callers can locate it. Empty when the rig is valid.
struct RigError {
  std::string path;
  std::string message;
};
std::vector<RigError> ValidateRig(const v1::RigConfig& rig, absl::string_view base_dir,
                                  const RigValidationOptions& options = {});

// Applies one what-if assignment "path=value" to `rig`, as `stagectl timing check --set` takes it. The path names
// fields as in the rig file; list entries are selected by id, index, "*" or a glob of ids:
// "timing.led_switch_delay_us=60", "cameras[hs-1].exposure_us=850", "cameras[mv-*].link=gige-1",
// "light_nodes[0].unit_limits.max_duty_cycle=0.4". The value is parsed by the rig file's rules (enum spellings, ranges
// of integers). Errors start with "--set <assignment>:" and name the field or id that does not exist.
absl::Status ApplyRigOverride(v1::RigConfig* rig, absl::string_view assignment);

// `loaded` with every assignment applied, defaults filled and the result validated; the source name says which
// overrides were applied. Without assignments, a copy of `loaded`.
absl::StatusOr<LoadedRig> ApplyRigOverrides(const LoadedRig& loaded, const std::vector<std::string>& assignments);

// The text of the shipped default rig (common/rigs/fastage.yaml, compiled in).
absl::string_view BuiltinRigText();

// A stable 64-bit FNV-1a hash of the rig's deterministic serialization, as 16 hex digits: same rig, same hash.
// Node addresses are left out: they are deployment detail that stage-sim assigns at run time.
std::string RigHash(const v1::RigConfig& rig);

// FNV-1a 64 of `bytes`, starting from `basis` (the standard offset basis unless given).
uint64_t Fnv1a64(absl::string_view bytes, uint64_t basis = 1469598103934665603ull);

// FNV-1a 64 of any message's deterministic serialization, 16 hex digits (RigHash, the schedule's hash).
std::string StableHash(const google::protobuf::Message& message);

// The GenICam PFNC name of a pixel format ("Mono8", "BayerRG8", ...); "" when unspecified.
std::string PixelFormatName(v1::PixelFormat format);

// "high-speed" or "machine-vision": a camera's role as status, stagectl and take summaries spell it.
std::string CameraRoleName(v1::CameraRole role);

// The entry for node `id`, or NotFound naming the id, the rig and the ids that exist.
absl::StatusOr<const v1::CameraConfig*> FindCamera(const LoadedRig& loaded, absl::string_view id);
absl::StatusOr<const v1::LightNodeConfig*> FindLightNode(const LoadedRig& loaded, absl::string_view id);
absl::StatusOr<const v1::ProcessingWorkerConfig*> FindProcessingWorker(const LoadedRig& loaded, absl::string_view id);

// Where stage-sim keeps its run directory (endpoint file, logs) unless told otherwise:
// $XDG_RUNTIME_DIR/fastage/stage-sim, or /tmp/fastage-<uid>/stage-sim.
std::string DefaultSimRunDir();
// Where this user's processes share what they derive from files (a head asset's decoded maps): $FASTAGE_CACHE_DIR,
// else $XDG_CACHE_HOME/fastage, else ~/.cache/fastage, else /tmp/fastage-<uid>/cache. What is there may be deleted at
// any time: it is made again.
std::string DefaultCacheDir();

// Pattern sets known without a file.
bool IsBuiltinPatternSet(absl::string_view name);

// Splits "host:port" (or "[v6]:port"); port must be 0..65535. Errors name the address.
absl::Status ParseHostPort(absl::string_view address, std::string* host, int* port);
// "host:port" for clients of a server bound to `host` (as ParseHostPort returned it) and `port`: a wildcard (0.0.0.0,
// ::) is dialled on loopback, an IPv6 address is bracketed.
std::string DialAddress(absl::string_view host, int port);

}  // namespace stage
