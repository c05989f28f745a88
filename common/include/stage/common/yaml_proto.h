// YAML text into a protobuf message, strictly: unknown fields, wrong types, duplicate keys and out-of-range
// numbers are errors that name the file, the line and the field path ("rig.yaml:42:5: cameras[3].width: ...").
// The schema is the message's descriptor, so every config message gets the same checks for free.
#pragma once

#include <map>
#include <string>

#include "absl/status/status.h"
#include "absl/strings/string_view.h"

namespace google::protobuf {
class Message;
}  // namespace google::protobuf

namespace stage {

// 1-based position of a value in the source text.
struct SourceLocation {
  int line = 0;
  int column = 0;
};

// Where each field path was written in the source, so that later (semantic) errors can point at the line too.
// Paths look like "cameras[3].trigger.divider" and "cameras[0].features[\"Gamma\"]".
class SourceMap {
 public:
  void Set(const std::string& path, SourceLocation location) { locations_[path] = location; }
  // The location of `path`, or of its nearest written ancestor ("cameras[3]" for a missing "cameras[3].width").
  // Returns a zero location if nothing on the path was written.
  SourceLocation Find(absl::string_view path) const;

 private:
  std::map<std::string, SourceLocation, std::less<>> locations_;
};

// Formats "<file>:<line>:<column>: <path>: <message>" (location parts left out when unknown).
std::string FormatConfigError(absl::string_view file_name, SourceLocation location, absl::string_view path,
                              absl::string_view message);

// Parses `text` (YAML; JSON is YAML too) into `message`, which it clears first. `file_name` is only used in error
// messages. Rules, beyond YAML itself:
//  - a map fills a message; keys are the proto field names; an unknown or repeated key is an error;
//  - a null value (`key:` or `key: ~`) leaves the field unset;
//  - enums accept the full value name or the name without the enum's prefix, in any case, with '-' for '_'
//    ("high-speed" for CAMERA_ROLE_HIGH_SPEED);
//  - a message whose fields are all numbers may be written as a list in field order ("[0, 1, 0]" for a Vec3);
//  - integers must be integral and fit their field (no negative values for unsigned fields);
//  - setting two members of one oneof is an error.
// On error `message` holds what was parsed so far. `source_map` (may be null) receives the location of every field.
absl::Status ParseYamlToProto(absl::string_view text, absl::string_view file_name, google::protobuf::Message* message,
                              SourceMap* source_map);

}  // namespace stage
