// What-if overrides of a rig: "path=value" assignments applied through the protobuf descriptor, with values parsed
// by the same strict rules as the rig file.
#include <fnmatch.h>
#include <google/protobuf/descriptor.h>
#include <google/protobuf/message.h>

#include <vector>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "stage/common/rig.h"
#include "stage/common/yaml_proto.h"

namespace stage {
namespace {

using google::protobuf::Descriptor;
using google::protobuf::FieldDescriptor;
using google::protobuf::Message;
using google::protobuf::Reflection;

struct Segment {
  std::string name;
  bool has_selector = false;
  std::string selector;
};

// "cameras[mv-01.a].trigger.delay_us" -> cameras[mv-01.a], trigger, delay_us. Ids may contain '.', so a selector
// runs to its ']'.
absl::StatusOr<std::vector<Segment>> SplitPath(absl::string_view path) {
  std::vector<Segment> out;
  size_t i = 0;
  while (i < path.size()) {
    Segment s;
    while (i < path.size() && path[i] != '.' && path[i] != '[') s.name.push_back(path[i++]);
    if (i < path.size() && path[i] == '[') {
      size_t close = path.find(']', i);
      if (close == absl::string_view::npos) return absl::InvalidArgumentError("unbalanced '['");
      s.has_selector = true;
      s.selector = std::string(path.substr(i + 1, close - i - 1));
      i = close + 1;
    }
    if (s.name.empty()) return absl::InvalidArgumentError("empty field name");
    out.push_back(std::move(s));
    if (i < path.size()) {
      if (path[i] != '.') return absl::InvalidArgumentError(absl::StrCat("unexpected '", path.substr(i, 1), "'"));
      ++i;
      if (i == path.size()) return absl::InvalidArgumentError("path ends with '.'");
    }
  }
  if (out.empty()) return absl::InvalidArgumentError("empty path");
  return out;
}

std::string FieldNames(const Descriptor* d) {
  std::vector<std::string> names;
  for (int i = 0; i < d->field_count(); ++i) names.push_back(d->field(i)->name());
  return absl::StrJoin(names, ", ");
}

// The elements of repeated message field `field` of `m` that `selector` picks: "*" all, a number by index (one past
// the last appends a new entry: sim.faults[0].target=mv-02 on a rig without faults), a glob ("mv-*") or an id.
absl::StatusOr<std::vector<Message*>> Select(Message* m, const FieldDescriptor* field, const std::string& selector) {
  const Reflection* r = m->GetReflection();
  const int n = r->FieldSize(*m, field);
  std::vector<Message*> out;
  if (selector == "*") {
    for (int i = 0; i < n; ++i) out.push_back(r->MutableRepeatedMessage(m, field, i));
    return out;
  }
  int index;
  if (absl::SimpleAtoi(selector, &index)) {
    if (index == n) {
      out.push_back(r->AddMessage(m, field));
      return out;
    }
    if (index < 0 || index > n) {
      return absl::InvalidArgumentError(
          absl::StrCat(field->name(), "[", selector, "]: index out of range (", n, " entries)"));
    }
    out.push_back(r->MutableRepeatedMessage(m, field, index));
    return out;
  }
  const FieldDescriptor* id = field->message_type()->FindFieldByName("id");
  if (id == nullptr || id->type() != FieldDescriptor::TYPE_STRING) {
    return absl::InvalidArgumentError(absl::StrCat(field->name(), " entries have no id; select them by index"));
  }
  std::vector<std::string> ids;
  for (int i = 0; i < n; ++i) {
    Message* e = r->MutableRepeatedMessage(m, field, i);
    std::string value = e->GetReflection()->GetString(*e, id);
    if (value == selector || fnmatch(selector.c_str(), value.c_str(), 0) == 0) out.push_back(e);
    ids.push_back(std::move(value));
  }
  if (out.empty()) {
    return absl::InvalidArgumentError(absl::StrCat("no ", field->name(), " entry with id \"", selector,
                                                   "\" (ids: ", ids.empty() ? "none" : absl::StrJoin(ids, ", "), ")"));
  }
  return out;
}

absl::Status Apply(Message* root, absl::string_view path, absl::string_view value) {
  auto segments = SplitPath(path);
  if (!segments.ok()) return segments.status();
  std::vector<Message*> targets = {root};
  for (size_t k = 0; k + 1 < segments->size(); ++k) {
    const Segment& s = (*segments)[k];
    const Descriptor* d = targets.front()->GetDescriptor();
    const FieldDescriptor* field = d->FindFieldByName(s.name);
    if (field == nullptr) {
      return absl::InvalidArgumentError(
          absl::StrCat(d->name(), " has no field \"", s.name, "\" (fields: ", FieldNames(d), ")"));
    }
    if (field->cpp_type() != FieldDescriptor::CPPTYPE_MESSAGE || field->is_map()) {
      return absl::InvalidArgumentError(absl::StrCat(s.name, " is not a message with fields"));
    }
    std::vector<Message*> next;
    for (Message* m : targets) {
      if (field->is_repeated()) {
        if (!s.has_selector) {
          return absl::InvalidArgumentError(absl::StrCat(s.name, " is a list: select entries with ", s.name, "[id], ",
                                                         s.name, "[index] or ", s.name, "[*]"));
        }
        auto picked = Select(m, field, s.selector);
        if (!picked.ok()) return picked.status();
        next.insert(next.end(), picked->begin(), picked->end());
      } else {
        if (s.has_selector) return absl::InvalidArgumentError(absl::StrCat(s.name, " is not a list"));
        next.push_back(m->GetReflection()->MutableMessage(m, field));
      }
    }
    if (next.empty()) {
      return absl::InvalidArgumentError(absl::StrCat(s.name, s.has_selector ? absl::StrCat("[", s.selector, "]") : "",
                                                     " selects no entries (the list is empty)"));
    }
    targets = std::move(next);
  }
  const Segment& last = segments->back();
  if (last.has_selector) {
    return absl::InvalidArgumentError(absl::StrCat("set the whole of ", last.name, " (e.g. ", last.name, "=[...])"));
  }
  const Descriptor* d = targets.front()->GetDescriptor();
  const FieldDescriptor* field = d->FindFieldByName(last.name);
  if (field == nullptr) {
    return absl::InvalidArgumentError(
        absl::StrCat(d->name(), " has no field \"", last.name, "\" (fields: ", FieldNames(d), ")"));
  }
  // Parse "name: value" into a fresh message of the target's type with the rig file's rules, then replace the field.
  std::unique_ptr<Message> parsed(targets.front()->New());
  absl::Status s = ParseYamlToProto(absl::StrCat(last.name, ": ", value), "", parsed.get(), nullptr);
  if (!s.ok()) {
    // Drop the location of the one-line document (": 1:7: ").
    std::string message(s.message());
    size_t cut = message.find(": ", message.find(": ") + 1);
    if (absl::StartsWith(message, ":") && cut != std::string::npos) message = message.substr(cut + 2);
    return absl::InvalidArgumentError(message);
  }
  for (Message* m : targets) {
    m->GetReflection()->ClearField(m, field);
    m->MergeFrom(*parsed);
  }
  return absl::OkStatus();
}

}  // namespace

absl::Status ApplyRigOverride(v1::RigConfig* rig, absl::string_view assignment) {
  const size_t eq = assignment.find('=');
  if (eq == absl::string_view::npos) {
    return absl::InvalidArgumentError(absl::StrCat("--set \"", assignment,
                                                   "\": expected path=value, e.g. timing.led_switch_delay_us=60 or "
                                                   "cameras[hs-1].exposure_us=850 or cameras[mv-*].link=gige-1"));
  }
  absl::string_view path = absl::StripAsciiWhitespace(assignment.substr(0, eq));
  absl::string_view value = absl::StripAsciiWhitespace(assignment.substr(eq + 1));
  absl::Status s = Apply(rig, path, value);
  if (!s.ok()) return absl::InvalidArgumentError(absl::StrCat("--set ", assignment, ": ", s.message()));
  return absl::OkStatus();
}

absl::StatusOr<LoadedRig> ApplyRigOverrides(const LoadedRig& loaded, const std::vector<std::string>& assignments) {
  if (assignments.empty()) return loaded;
  LoadedRig out = loaded;
  // On the rig as written: the defaults are filled after the overrides, so those that follow a field follow its new
  // value.
  v1::RigConfig written = loaded.as_written.value_or(loaded.rig);
  for (const std::string& a : assignments) {
    absl::Status s = ApplyRigOverride(&written, a);
    if (!s.ok()) return s;
  }
  out.as_written = written;
  out.rig = std::move(written);
  ApplyRigDefaults(&out.rig);
  std::vector<RigError> errors = ValidateRig(out.rig, out.base_dir);
  if (!errors.empty()) {
    std::vector<std::string> lines;
    for (const RigError& e : errors) lines.push_back(absl::StrCat(e.path, ": ", e.message));
    return absl::InvalidArgumentError(
        absl::StrCat("the rig with ", absl::StrJoin(assignments, ", "), " is not valid: ", absl::StrJoin(lines, "; ")));
  }
  out.source_name = absl::StrCat(loaded.source_name, " with ", absl::StrJoin(assignments, ", "));
  return out;
}

}  // namespace stage
