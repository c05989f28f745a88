// Strict YAML -> protobuf conversion driven by the message descriptor.
#include "stage/common/yaml_proto.h"

#include <google/protobuf/descriptor.h>
#include <google/protobuf/message.h>
#include <google/protobuf/reflection.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <set>
#include <vector>

#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_replace.h"

namespace stage {
namespace {

using google::protobuf::Descriptor;
using google::protobuf::EnumDescriptor;
using google::protobuf::EnumValueDescriptor;
using google::protobuf::FieldDescriptor;
using google::protobuf::Message;
using google::protobuf::Reflection;

SourceLocation ToLocation(const YAML::Mark& mark) {
  if (mark.is_null()) return {};
  return {mark.line + 1, mark.column + 1};
}

const char* NodeTypeName(const YAML::Node& node) {
  switch (node.Type()) {
    case YAML::NodeType::Map:
      return "a map";
    case YAML::NodeType::Sequence:
      return "a list";
    case YAML::NodeType::Scalar:
      return "a scalar";
    case YAML::NodeType::Null:
      return "nothing";
    default:
      return "an undefined value";
  }
}

// Levenshtein distance, for "did you mean" suggestions on unknown keys.
size_t EditDistance(absl::string_view a, absl::string_view b) {
  std::vector<size_t> row(b.size() + 1);
  for (size_t j = 0; j <= b.size(); ++j) row[j] = j;
  for (size_t i = 1; i <= a.size(); ++i) {
    size_t diagonal = row[0];
    row[0] = i;
    for (size_t j = 1; j <= b.size(); ++j) {
      size_t above = row[j];
      row[j] = std::min({row[j] + 1, row[j - 1] + 1, diagonal + (a[i - 1] == b[j - 1] ? 0 : 1)});
      diagonal = above;
    }
  }
  return row[b.size()];
}

// The enum value names a user may write: "CAMERA_ROLE_HIGH_SPEED" is also "high-speed" / "HIGH_SPEED".
std::string ShortEnumName(const EnumValueDescriptor* value) {
  // CamelCase type name -> UPPER_SNAKE prefix: CameraRole -> CAMERA_ROLE_.
  std::string snake;
  for (char c : value->type()->name()) {
    if (absl::ascii_isupper(c) && !snake.empty()) snake.push_back('_');
    snake.push_back(absl::ascii_toupper(c));
  }
  snake.push_back('_');
  std::string name = value->name();
  if (name.rfind(snake, 0) == 0) name = name.substr(snake.size());
  return absl::StrReplaceAll(absl::AsciiStrToLower(name), {{"_", "-"}});
}

std::string NormalizeEnumInput(absl::string_view text) {
  return absl::StrReplaceAll(absl::AsciiStrToLower(absl::StripAsciiWhitespace(text)), {{"_", "-"}});
}

class Parser {
 public:
  Parser(absl::string_view file_name, SourceMap* source_map) : file_name_(file_name), source_map_(source_map) {}

  absl::Status ParseMessage(const YAML::Node& node, const std::string& path, Message* message) {
    const Descriptor* descriptor = message->GetDescriptor();
    if (node.IsSequence() && AllFieldsNumeric(descriptor)) return ParsePositional(node, path, message);
    if (!node.IsMap()) {
      return Error(node, path,
                   absl::StrCat("expected a map of ", descriptor->name(), " fields, got ", NodeTypeName(node)));
    }
    const Reflection* reflection = message->GetReflection();
    std::set<std::string> seen;
    for (const auto& entry : node) {
      const YAML::Node& key = entry.first;
      const YAML::Node& value = entry.second;
      if (!key.IsScalar()) return Error(key, path, "map keys must be plain names");
      const std::string& name = key.Scalar();
      std::string field_path = path.empty() ? name : absl::StrCat(path, ".", name);
      if (!seen.insert(name).second) return Error(key, field_path, "duplicate key");
      const FieldDescriptor* field = descriptor->FindFieldByName(name);
      if (field == nullptr) return Error(key, field_path, UnknownFieldMessage(descriptor, name));
      Record(field_path, key);
      if (value.IsNull()) continue;
      if (const auto* oneof = field->real_containing_oneof(); oneof != nullptr) {
        const FieldDescriptor* other = reflection->GetOneofFieldDescriptor(*message, oneof);
        if (other != nullptr && other != field) {
          std::vector<std::string> members;
          for (int i = 0; i < oneof->field_count(); ++i) members.push_back(oneof->field(i)->name());
          return Error(key, field_path,
                       absl::StrCat("only one of ", absl::StrJoin(members, ", "), " may be set, and ", other->name(),
                                    " is set already"));
        }
      }
      absl::Status status = ParseField(value, field_path, field, message);
      if (!status.ok()) return status;
    }
    return absl::OkStatus();
  }

 private:
  static bool AllFieldsNumeric(const Descriptor* descriptor) {
    if (descriptor->field_count() == 0) return false;
    for (int i = 0; i < descriptor->field_count(); ++i) {
      const FieldDescriptor* f = descriptor->field(i);
      if (f->is_repeated()) return false;
      switch (f->cpp_type()) {
        case FieldDescriptor::CPPTYPE_DOUBLE:
        case FieldDescriptor::CPPTYPE_FLOAT:
        case FieldDescriptor::CPPTYPE_INT32:
        case FieldDescriptor::CPPTYPE_INT64:
        case FieldDescriptor::CPPTYPE_UINT32:
        case FieldDescriptor::CPPTYPE_UINT64:
          break;
        default:
          return false;
      }
    }
    return true;
  }

  // "[1, 2, 3]" for a message of three numbers, in field order.
  absl::Status ParsePositional(const YAML::Node& node, const std::string& path, Message* message) {
    const Descriptor* descriptor = message->GetDescriptor();
    if (static_cast<int>(node.size()) != descriptor->field_count()) {
      std::vector<std::string> names;
      for (int i = 0; i < descriptor->field_count(); ++i) names.push_back(descriptor->field(i)->name());
      return Error(node, path,
                   absl::StrCat("expected a list of ", descriptor->field_count(), " numbers [",
                                absl::StrJoin(names, ", "), "], got ", node.size()));
    }
    for (int i = 0; i < descriptor->field_count(); ++i) {
      const FieldDescriptor* field = descriptor->field(i);
      std::string field_path = absl::StrCat(path, ".", field->name());
      Record(field_path, node[i]);
      absl::Status status = SetScalar(node[i], field_path, field, message, /*repeated=*/false);
      if (!status.ok()) return status;
    }
    return absl::OkStatus();
  }

  absl::Status ParseField(const YAML::Node& value, const std::string& path, const FieldDescriptor* field,
                          Message* message) {
    const Reflection* reflection = message->GetReflection();
    if (field->is_map()) {
      if (!value.IsMap()) return Error(value, path, absl::StrCat("expected a map, got ", NodeTypeName(value)));
      const Descriptor* entry_type = field->message_type();
      const FieldDescriptor* key_field = entry_type->map_key();
      const FieldDescriptor* value_field = entry_type->map_value();
      std::set<std::string> seen;
      for (const auto& entry : value) {
        if (!entry.first.IsScalar()) return Error(entry.first, path, "map keys must be scalars");
        std::string entry_path = absl::StrCat(path, "[\"", entry.first.Scalar(), "\"]");
        if (!seen.insert(entry.first.Scalar()).second) return Error(entry.first, entry_path, "duplicate key");
        Record(entry_path, entry.first);
        Message* item = reflection->AddMessage(message, field);
        absl::Status status = SetScalar(entry.first, entry_path, key_field, item, false);
        if (status.ok()) status = ParseValue(entry.second, entry_path, value_field, item, false);
        if (!status.ok()) return status;
      }
      return absl::OkStatus();
    }
    if (field->is_repeated()) {
      if (!value.IsSequence()) {
        return Error(value, path, absl::StrCat("expected a list, got ", NodeTypeName(value)));
      }
      for (size_t i = 0; i < value.size(); ++i) {
        std::string item_path = absl::StrCat(path, "[", i, "]");
        Record(item_path, value[i]);
        absl::Status status = ParseValue(value[i], item_path, field, message, /*repeated=*/true);
        if (!status.ok()) return status;
      }
      return absl::OkStatus();
    }
    return ParseValue(value, path, field, message, /*repeated=*/false);
  }

  absl::Status ParseValue(const YAML::Node& value, const std::string& path, const FieldDescriptor* field,
                          Message* message, bool repeated) {
    const Reflection* reflection = message->GetReflection();
    if (field->cpp_type() == FieldDescriptor::CPPTYPE_MESSAGE) {
      Message* child = repeated ? reflection->AddMessage(message, field) : reflection->MutableMessage(message, field);
      if (value.IsNull()) return absl::OkStatus();
      return ParseMessage(value, path, child);
    }
    return SetScalar(value, path, field, message, repeated);
  }

  absl::Status SetScalar(const YAML::Node& value, const std::string& path, const FieldDescriptor* field,
                         Message* message, bool repeated) {
    if (!value.IsScalar()) {
      return Error(value, path, absl::StrCat("expected ", ExpectedName(field), ", got ", NodeTypeName(value)));
    }
    const Reflection* r = message->GetReflection();
    const std::string& text = value.Scalar();
    auto bad = [&](absl::string_view why) {
      return Error(value, path, absl::StrCat("\"", text, "\" is not ", ExpectedName(field), why));
    };
    switch (field->cpp_type()) {
      case FieldDescriptor::CPPTYPE_STRING:
        repeated ? r->AddString(message, field, text) : r->SetString(message, field, text);
        return absl::OkStatus();
      case FieldDescriptor::CPPTYPE_BOOL: {
        std::string lower = absl::AsciiStrToLower(text);
        bool v;
        if (lower == "true" || lower == "yes" || lower == "on") {
          v = true;
        } else if (lower == "false" || lower == "no" || lower == "off") {
          v = false;
        } else {
          return bad(" (true or false)");
        }
        repeated ? r->AddBool(message, field, v) : r->SetBool(message, field, v);
        return absl::OkStatus();
      }
      case FieldDescriptor::CPPTYPE_DOUBLE:
      case FieldDescriptor::CPPTYPE_FLOAT: {
        double v;
        if (!absl::SimpleAtod(text, &v) || !std::isfinite(v)) return bad("");
        if (field->cpp_type() == FieldDescriptor::CPPTYPE_DOUBLE) {
          repeated ? r->AddDouble(message, field, v) : r->SetDouble(message, field, v);
        } else {
          auto f = static_cast<float>(v);
          repeated ? r->AddFloat(message, field, f) : r->SetFloat(message, field, f);
        }
        return absl::OkStatus();
      }
      case FieldDescriptor::CPPTYPE_INT32:
      case FieldDescriptor::CPPTYPE_INT64: {
        int64_t v;
        if (!absl::SimpleAtoi(text, &v)) return bad(IntegerHint(text));
        if (field->cpp_type() == FieldDescriptor::CPPTYPE_INT32) {
          if (v < std::numeric_limits<int32_t>::min() || v > std::numeric_limits<int32_t>::max()) {
            return bad(" (out of range for a 32-bit integer)");
          }
          auto i = static_cast<int32_t>(v);
          repeated ? r->AddInt32(message, field, i) : r->SetInt32(message, field, i);
        } else {
          repeated ? r->AddInt64(message, field, v) : r->SetInt64(message, field, v);
        }
        return absl::OkStatus();
      }
      case FieldDescriptor::CPPTYPE_UINT32:
      case FieldDescriptor::CPPTYPE_UINT64: {
        absl::string_view stripped = absl::StripAsciiWhitespace(text);
        if (!stripped.empty() && stripped[0] == '-') {
          return Error(value, path, absl::StrCat(text, " is negative; expected an integer >= 0"));
        }
        uint64_t v;
        if (!absl::SimpleAtoi(text, &v)) return bad(IntegerHint(text));
        if (field->cpp_type() == FieldDescriptor::CPPTYPE_UINT32) {
          if (v > std::numeric_limits<uint32_t>::max()) return bad(" (out of range for a 32-bit integer)");
          auto u = static_cast<uint32_t>(v);
          repeated ? r->AddUInt32(message, field, u) : r->SetUInt32(message, field, u);
        } else {
          repeated ? r->AddUInt64(message, field, v) : r->SetUInt64(message, field, v);
        }
        return absl::OkStatus();
      }
      case FieldDescriptor::CPPTYPE_ENUM: {
        const EnumDescriptor* type = field->enum_type();
        const EnumValueDescriptor* found = nullptr;
        std::string wanted = NormalizeEnumInput(text);
        std::vector<std::string> valid;
        for (int i = 0; i < type->value_count(); ++i) {
          const EnumValueDescriptor* v = type->value(i);
          if (v->number() == 0) continue;  // *_UNSPECIFIED is never a valid choice
          valid.push_back(ShortEnumName(v));
          if (wanted == ShortEnumName(v) || wanted == NormalizeEnumInput(v->name())) found = v;
        }
        if (found == nullptr) {
          return Error(value, path,
                       absl::StrCat("\"", text, "\" is not a valid ", type->name(),
                                    "; valid values: ", absl::StrJoin(valid, ", ")));
        }
        repeated ? r->AddEnum(message, field, found) : r->SetEnum(message, field, found);
        return absl::OkStatus();
      }
      case FieldDescriptor::CPPTYPE_MESSAGE:
        break;
    }
    return Error(value, path, "internal error: unexpected field type");
  }

  static std::string IntegerHint(const std::string& text) {
    double d;
    if (absl::SimpleAtod(text, &d) && std::isfinite(d)) {
      if (d != std::floor(d)) return " (it has a fraction)";
      return " (out of range)";
    }
    return "";
  }

  static std::string ExpectedName(const FieldDescriptor* field) {
    switch (field->cpp_type()) {
      case FieldDescriptor::CPPTYPE_STRING:
        return "a string";
      case FieldDescriptor::CPPTYPE_BOOL:
        return "a boolean";
      case FieldDescriptor::CPPTYPE_DOUBLE:
      case FieldDescriptor::CPPTYPE_FLOAT:
        return "a number";
      case FieldDescriptor::CPPTYPE_INT32:
      case FieldDescriptor::CPPTYPE_INT64:
        return "an integer";
      case FieldDescriptor::CPPTYPE_UINT32:
      case FieldDescriptor::CPPTYPE_UINT64:
        return "an integer >= 0";
      case FieldDescriptor::CPPTYPE_ENUM:
        return absl::StrCat("a ", field->enum_type()->name(), " name");
      case FieldDescriptor::CPPTYPE_MESSAGE:
        return absl::StrCat("a map of ", field->message_type()->name(), " fields");
    }
    return "a value";
  }

  static std::string UnknownFieldMessage(const Descriptor* descriptor, const std::string& name) {
    std::vector<std::string> names;
    std::string closest;
    size_t best = 4;  // suggest only close matches
    for (int i = 0; i < descriptor->field_count(); ++i) {
      const std::string& candidate = descriptor->field(i)->name();
      names.push_back(candidate);
      size_t d = EditDistance(absl::AsciiStrToLower(name), candidate);
      if (d < best) {
        best = d;
        closest = candidate;
      }
    }
    std::string message = absl::StrCat("unknown field \"", name, "\" in ", descriptor->name());
    if (!closest.empty()) return absl::StrCat(message, " (did you mean \"", closest, "\"?)");
    return absl::StrCat(message, "; valid fields: ", absl::StrJoin(names, ", "));
  }

  void Record(const std::string& path, const YAML::Node& node) {
    if (source_map_ != nullptr) source_map_->Set(path, ToLocation(node.Mark()));
  }

  absl::Status Error(const YAML::Node& node, const std::string& path, absl::string_view message) const {
    return absl::InvalidArgumentError(FormatConfigError(file_name_, ToLocation(node.Mark()), path, message));
  }

  std::string file_name_;
  SourceMap* source_map_;
};

}  // namespace

SourceLocation SourceMap::Find(absl::string_view path) const {
  absl::string_view p = path;
  while (!p.empty()) {
    if (auto it = locations_.find(p); it != locations_.end()) return it->second;
    size_t cut = p.find_last_of(".[");
    if (cut == absl::string_view::npos) break;
    p = p.substr(0, cut);
  }
  return {};
}

std::string FormatConfigError(absl::string_view file_name, SourceLocation location, absl::string_view path,
                              absl::string_view message) {
  std::string out(file_name);
  if (location.line > 0) absl::StrAppend(&out, ":", location.line);
  if (location.column > 0) absl::StrAppend(&out, ":", location.column);
  absl::StrAppend(&out, ": ");
  if (!path.empty()) absl::StrAppend(&out, path, ": ");
  absl::StrAppend(&out, message);
  return out;
}

absl::Status ParseYamlToProto(absl::string_view text, absl::string_view file_name, google::protobuf::Message* message,
                              SourceMap* source_map) {
  message->Clear();
  YAML::Node root;
  try {
    root = YAML::Load(std::string(text));
  } catch (const YAML::Exception& e) {
    return absl::InvalidArgumentError(
        FormatConfigError(file_name, ToLocation(e.mark), "", absl::StrCat("YAML syntax error: ", e.msg)));
  }
  if (root.IsNull()) {
    return absl::InvalidArgumentError(FormatConfigError(
        file_name, {}, "",
        absl::StrCat("the file is empty; expected a map of ", message->GetDescriptor()->name(), " fields")));
  }
  Parser parser(file_name, source_map);
  try {
    return parser.ParseMessage(root, "", message);
  } catch (const YAML::Exception& e) {
    return absl::InvalidArgumentError(FormatConfigError(file_name, ToLocation(e.mark), "", e.msg));
  }
}

}  // namespace stage
