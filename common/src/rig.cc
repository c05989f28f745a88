// Rig loading: parse, defaults, validation.
#include "stage/common/rig.h"

#include <arpa/inet.h>
#include <google/protobuf/io/coded_stream.h>
#include <google/protobuf/io/zero_copy_stream_impl_lite.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <map>
#include <numeric>
#include <set>

#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "stage/common/file_util.h"
#include "stage/common/status.h"

extern const char kFastageRigYaml[];

namespace stage {
namespace {

using v1::CameraConfig;
using v1::LightNodeConfig;
using v1::RigConfig;

constexpr absl::string_view kFastage38 = "fastage-38";
// In fastage-38 the cross-polarized patterns come first: slot 19 of each 38 is the parallel full-on one.
constexpr uint32_t kFastage38Length = 38;
constexpr uint32_t kFastage38ParallelFullOn = 19;

bool IsRoleHighSpeed(const CameraConfig& c) { return c.role() == v1::CAMERA_ROLE_HIGH_SPEED; }

void ApplyLimitDefaults(v1::LedLimits* limits) {
  if (!limits->has_max_duty_cycle()) limits->set_max_duty_cycle(0.5);
  if (!limits->has_thermal_time_constant_s()) limits->set_thermal_time_constant_s(2.0);
  if (!limits->has_rise_us()) limits->set_rise_us(5.0);
  if (!limits->has_fall_us()) limits->set_fall_us(5.0);
}

// Collects errors with their field paths.
class Checker {
 public:
  void Add(std::string path, std::string message) { errors_.push_back({std::move(path), std::move(message)}); }

  // Number checks; `what` describes the bound for the message.
  void Positive(const std::string& path, double v) {
    if (!(v > 0)) Add(path, absl::StrCat(Num(v), " is not > 0"));
  }
  void InRange(const std::string& path, double v, double lo, double hi) {
    if (!(v >= lo && v <= hi)) Add(path, absl::StrCat(Num(v), " is not in [", Num(lo), ", ", Num(hi), "]"));
  }
  void Required(const std::string& path, bool present) {
    if (!present) Add(path, "required field is missing");
  }
  // A node or unit id: non-empty, [A-Za-z0-9._-], at most 64 characters.
  void Id(const std::string& path, const std::string& id) {
    if (id.empty()) {
      Add(path, "required field is missing");
      return;
    }
    bool ok = id.size() <= 64;
    for (char c : id) ok = ok && (absl::ascii_isalnum(c) || c == '-' || c == '_' || c == '.');
    if (!ok) Add(path, absl::StrCat("\"", id, "\" is not a valid id (letters, digits, '-', '_', '.'; <= 64 chars)"));
  }

  static std::string Num(double v) { return absl::StrFormat("%g", v); }

  std::vector<RigError> Take() { return std::move(errors_); }

 private:
  std::vector<RigError> errors_;
};

void CheckAddress(Checker& check, const std::string& path, const std::string& address, bool required) {
  if (address.empty()) {
    if (required) check.Add(path, "required by stage-controller (host:port of the node)");
    return;
  }
  std::string host;
  int port;
  if (absl::Status s = ParseHostPort(address, &host, &port); !s.ok()) {
    check.Add(path, std::string(s.message()));
  } else if (port == 0) {
    check.Add(path, absl::StrCat("\"", address, "\" has port 0; a node's address needs its real port"));
  }
}

void CheckLimits(Checker& check, const std::string& path, const v1::LedLimits& limits) {
  check.Required(path + ".max_current_ma", limits.has_max_current_ma());
  if (limits.has_max_current_ma()) check.InRange(path + ".max_current_ma", limits.max_current_ma(), 1e-3, 100000);
  if (!(limits.max_duty_cycle() > 0 && limits.max_duty_cycle() <= 1)) {
    check.Add(path + ".max_duty_cycle", absl::StrCat(Checker::Num(limits.max_duty_cycle()), " is not in (0, 1]"));
  }
  check.Positive(path + ".thermal_time_constant_s", limits.thermal_time_constant_s());
  check.InRange(path + ".rise_us", limits.rise_us(), 0, 1000);
  check.InRange(path + ".fall_us", limits.fall_us(), 0, 1000);
}

void CheckCamera(Checker& check, const std::string& p, const CameraConfig& c, const RigValidationOptions& options) {
  check.Id(p + ".id", c.id());
  if (c.role() == v1::CAMERA_ROLE_UNSPECIFIED) {
    check.Add(p + ".role", "required field is missing (machine-vision or high-speed)");
  }
  if (c.backend() == v1::CAMERA_BACKEND_ARAVIS && c.device().empty()) {
    check.Add(p + ".device", "required for the aravis backend (serial number, user id or IP address)");
  }
  CheckAddress(check, p + ".address", c.address(), options.require_addresses);
  check.Required(p + ".width", c.has_width());
  check.Required(p + ".height", c.has_height());
  if (c.has_width()) check.InRange(p + ".width", c.width(), 1, 65535);
  if (c.has_height()) check.InRange(p + ".height", c.height(), 1, 65535);
  check.InRange(p + ".frame_rate_hz", c.frame_rate_hz(), 1e-3, 100000);
  check.Required(p + ".exposure_us", c.has_exposure_us());
  if (c.has_exposure_us()) {
    check.Positive(p + ".exposure_us", c.exposure_us());
    double period_us = c.frame_rate_hz() > 0 ? 1e6 / c.frame_rate_hz() : 0;
    if (c.exposure_us() > 0 && period_us > 0 && c.exposure_us() >= period_us) {
      check.Add(p + ".exposure_us", absl::StrFormat("%g us is not shorter than the frame period %.3f us at %g fps",
                                                    c.exposure_us(), period_us, c.frame_rate_hz()));
    }
  }
  check.InRange(p + ".gain_db", c.gain_db(), 0, 48);
  check.InRange(p + ".readout_us", c.readout_us(), 0, 1e7);
  check.InRange(p + ".max_frame_rate_hz", c.max_frame_rate_hz(), 0, 1e6);
  check.InRange(p + ".packet_size", c.packet_size(), 576, 16384);
  check.InRange(p + ".frame_buffer_mib", c.frame_buffer_mib(), 0, 1e7);
  check.InRange(p + ".offset_x", c.offset_x(), 0, 65535);
  check.InRange(p + ".offset_y", c.offset_y(), 0, 65535);
  check.InRange(p + ".binning", c.binning(), 1, 16);
  check.InRange(p + ".gige.buffers", c.gige().buffers(), 2, 4096);
  check.InRange(p + ".gige.packet_delay_ns", c.gige().packet_delay_ns(), 0, 1e9);
  check.InRange(p + ".gige.reconnect_max_s", c.gige().reconnect_max_s(), 0.01, 3600);
  if (c.trigger().has_delay_us()) check.InRange(p + ".trigger.delay_us", c.trigger().delay_us(), 0, 1e7);
  const auto& t = c.trigger();
  if (t.divider() < 1) check.Add(p + ".trigger.divider", "0 is not >= 1");
  if (!t.has_divider()) {
    check.Add(p + ".trigger.divider",
              absl::StrCat("required when pattern_set is not ", kFastage38, " (no default divider)"));
  }
  if (!t.has_slot_phase()) {
    check.Add(p + ".trigger.slot_phase",
              absl::StrCat("required when pattern_set is not ", kFastage38, " (no default phase)"));
  } else if (t.divider() >= 1 && t.slot_phase() >= t.divider()) {
    check.Add(p + ".trigger.slot_phase", absl::StrCat(t.slot_phase(), " is not < the divider ", t.divider()));
  }
  check.InRange(p + ".ram_gib", c.ram_gib(), 0, 1e6);
  if (IsRoleHighSpeed(c) && c.link() == v1::LINK_KIND_ON_CAMERA_RAM && !(c.ram_gib() > 0)) {
    check.Add(p + ".ram_gib", "required (> 0) for a high-speed camera that records to on-camera RAM");
  }
  check.Positive(p + ".intrinsics.focal_length_mm", c.intrinsics().focal_length_mm());
  check.Positive(p + ".intrinsics.pixel_size_um", c.intrinsics().pixel_size_um());
  if (c.intrinsics().distortion_size() > 5) {
    check.Add(p + ".intrinsics.distortion",
              absl::StrCat("has ", c.intrinsics().distortion_size(), " coefficients; at most 5 (k1, k2, p1, p2, k3)"));
  }
  const auto& pose = c.pose();
  if (!c.has_pose()) {
    check.Add(p + ".pose", "required field is missing (position_mm of the camera in the stage frame)");
  } else {
    double dx = pose.position_mm().x() - pose.look_at_mm().x();
    double dy = pose.position_mm().y() - pose.look_at_mm().y();
    double dz = pose.position_mm().z() - pose.look_at_mm().z();
    if (std::sqrt(dx * dx + dy * dy + dz * dz) < 1.0) {
      check.Add(p + ".pose.look_at_mm", "is the camera position itself; it must be a point the camera looks at");
    }
  }
}

void CheckLightNode(Checker& check, const std::string& p, const LightNodeConfig& n, const RigValidationOptions& options,
                    std::map<std::string, std::string>* unit_ids) {
  check.Id(p + ".id", n.id());
  CheckAddress(check, p + ".address", n.address(), options.require_addresses);
  check.Required(p + ".channel_count", n.has_channel_count());
  if (n.has_channel_count()) check.InRange(p + ".channel_count", n.channel_count(), 1, 4096);
  if (n.has_switch_delay_us()) check.InRange(p + ".switch_delay_us", n.switch_delay_us(), 0, 1e6);
  switch (n.backend()) {
    case v1::LIGHT_BACKEND_SIM:
      if (n.device_case() != LightNodeConfig::kSim && n.device_case() != LightNodeConfig::DEVICE_NOT_SET) {
        check.Add(p + (n.has_gpiod() ? ".gpiod" : ".modbus"), "is set, but backend is sim");
      }
      break;
    case v1::LIGHT_BACKEND_GPIOD:
      if (!n.has_gpiod()) {
        check.Add(p + ".gpiod", "required for backend gpiod (chip and channel_lines)");
      } else {
        if (n.gpiod().chip().empty()) check.Add(p + ".gpiod.chip", "required field is missing");
        const uint32_t per = n.gpiod().has_lines_per_channel() ? n.gpiod().lines_per_channel() : 1;
        check.InRange(p + ".gpiod.lines_per_channel", per, 1, 16);
        if (static_cast<uint32_t>(n.gpiod().channel_lines_size()) != n.channel_count() * per) {
          check.Add(p + ".gpiod.channel_lines",
                    absl::StrCat("has ", n.gpiod().channel_lines_size(),
                                 " lines; channel_count x lines_per_channel is ", n.channel_count() * per));
        }
        std::set<uint32_t> lines(n.gpiod().channel_lines().begin(), n.gpiod().channel_lines().end());
        if (lines.size() != static_cast<size_t>(n.gpiod().channel_lines_size())) {
          check.Add(p + ".gpiod.channel_lines", "lists a line twice");
        }
        if (!n.gpiod().has_slot_clock_line()) {
          check.Add(p + ".gpiod.slot_clock_line", "required for backend gpiod (the node steps on it, or drives it)");
        } else if (lines.count(n.gpiod().slot_clock_line()) > 0) {
          check.Add(p + ".gpiod.slot_clock_line",
                    absl::StrCat("line ", n.gpiod().slot_clock_line(), " is also a channel line"));
        }
      }
      break;
    case v1::LIGHT_BACKEND_MODBUS:
      if (!n.has_modbus()) {
        check.Add(p + ".modbus", "required for backend modbus (tcp or rtu settings)");
      } else {
        const auto& m = n.modbus();
        if (m.transport_case() == v1::ModbusLightSettings::TRANSPORT_NOT_SET) {
          check.Add(p + ".modbus", "needs tcp or rtu");
        } else if (m.has_tcp()) {
          if (m.tcp().host().empty()) check.Add(p + ".modbus.tcp.host", "required field is missing");
          check.InRange(p + ".modbus.tcp.port", m.tcp().port(), 1, 65535);
        } else {
          if (m.rtu().device().empty()) check.Add(p + ".modbus.rtu.device", "required field is missing");
          check.Positive(p + ".modbus.rtu.baud", m.rtu().baud());
          if (m.rtu().parity() != "N" && m.rtu().parity() != "E" && m.rtu().parity() != "O") {
            check.Add(p + ".modbus.rtu.parity", absl::StrCat("\"", m.rtu().parity(), "\" is not N, E or O"));
          }
          check.InRange(p + ".modbus.rtu.data_bits", m.rtu().data_bits(), 5, 8);
          check.InRange(p + ".modbus.rtu.stop_bits", m.rtu().stop_bits(), 1, 2);
        }
        check.InRange(p + ".modbus.unit_id", m.unit_id(), 1, 247);
        check.InRange(p + ".modbus.timeout_ms", m.timeout_ms(), 1, 60000);
      }
      break;
    default:
      check.Add(p + ".backend", "required field is missing (sim, gpiod or modbus)");
  }
  if (!n.has_unit_limits()) {
    check.Add(p + ".unit_limits", "required field is missing (max_current_ma at least)");
  } else {
    CheckLimits(check, p + ".unit_limits", n.unit_limits());
  }
  std::map<uint32_t, std::string> channels;  // channel -> the path that uses it
  for (int i = 0; i < n.units_size(); ++i) {
    const auto& u = n.units(i);
    std::string up = absl::StrCat(p, ".units[", i, "]");
    check.Id(up + ".id", u.id());
    if (!u.id().empty()) {
      auto [it, inserted] = unit_ids->emplace(u.id(), up);
      if (!inserted)
        check.Add(up + ".id", absl::StrCat("duplicate LED unit id \"", u.id(), "\" (also ", it->second, ")"));
    }
    const auto& d = u.direction();
    double len = std::sqrt(d.x() * d.x() + d.y() * d.y() + d.z() * d.z());
    if (!u.has_direction()) {
      check.Add(up + ".direction", "required field is missing");
    } else if (std::abs(len - 1.0) > 1e-3) {
      check.Add(up + ".direction", absl::StrFormat("is not a unit vector (length %.4f)", len));
    }
    for (auto [present, channel, name] :
         {std::tuple{u.has_parallel_channel(), u.parallel_channel(), "parallel_channel"},
          std::tuple{u.has_cross_channel(), u.cross_channel(), "cross_channel"}}) {
      std::string cp = absl::StrCat(up, ".", name);
      if (!present) {
        check.Add(cp, "required field is missing");
        continue;
      }
      if (n.has_channel_count() && channel >= n.channel_count()) {
        check.Add(cp, absl::StrCat(channel, " is not < channel_count ", n.channel_count()));
        continue;
      }
      auto [it, inserted] = channels.emplace(channel, cp);
      if (!inserted) check.Add(cp, absl::StrCat("channel ", channel, " is already used by ", it->second));
    }
    if (!(u.intensity_scale() > 0 && u.intensity_scale() <= 10)) {
      check.Add(up + ".intensity_scale", absl::StrCat(Checker::Num(u.intensity_scale()), " is not in (0, 10]"));
    }
    if (u.has_limits()) CheckLimits(check, up + ".limits", u.limits());
  }
}

}  // namespace

bool IsBuiltinPatternSet(absl::string_view name) { return name == kFastage38; }

absl::string_view BuiltinRigText() { return kFastageRigYaml; }

absl::Status ParseHostPort(absl::string_view address, std::string* host, int* port) {
  size_t colon = address.rfind(':');
  auto bad = [&](absl::string_view why) {
    return absl::InvalidArgumentError(absl::StrCat("\"", address, "\" is not host:port (", why, ")"));
  };
  if (colon == absl::string_view::npos || colon == 0) return bad("missing host or port");
  absl::string_view h = address.substr(0, colon);
  if (h.front() == '[') {
    if (h.back() != ']') return bad("unbalanced '['");
    h = h.substr(1, h.size() - 2);
  } else if (h.find(':') != absl::string_view::npos) {
    return bad("write IPv6 addresses as [addr]:port");
  }
  int p;
  if (!absl::SimpleAtoi(address.substr(colon + 1), &p) || p < 0 || p > 65535) return bad("port is not 0..65535");
  if (h.empty()) return bad("empty host");
  *host = std::string(h);
  *port = p;
  return absl::OkStatus();
}

std::string DialAddress(absl::string_view host, int port) {
  if (host == "0.0.0.0" || host == "::") host = "127.0.0.1";
  return host.find(':') != absl::string_view::npos ? absl::StrCat("[", host, "]:", port)
                                                   : absl::StrCat(host, ":", port);
}

void ApplyRigDefaults(RigConfig* rig) {
  auto* controller = rig->mutable_controller();
  if (controller->listen().empty()) controller->set_listen("127.0.0.1:50050");
  if (!controller->has_health_poll_interval_ms()) controller->set_health_poll_interval_ms(200);
  if (!rig->security().has_reload_interval_s()) rig->mutable_security()->set_reload_interval_s(5);
  if (!controller->has_health_timeout_ms()) controller->set_health_timeout_ms(500);
  if (!controller->has_clock_sync_interval_ms()) controller->set_clock_sync_interval_ms(1000);
  if (!controller->has_clock_sync_burst()) controller->set_clock_sync_burst(8);
  if (!controller->has_take_stall_s()) controller->set_take_stall_s(120);
  if (controller->node_failure_policy() == v1::NODE_FAILURE_POLICY_UNSPECIFIED) {
    controller->set_node_failure_policy(v1::NODE_FAILURE_POLICY_CONTINUE_DEGRADED);
  }
  auto* timing = rig->mutable_timing();
  if (!timing->has_slot_rate_hz()) timing->set_slot_rate_hz(912);
  if (!timing->has_led_switch_delay_us()) timing->set_led_switch_delay_us(20);
  if (!timing->has_led_settle_us()) timing->set_led_settle_us(30);
  if (!timing->has_exposure_guard_us()) timing->set_exposure_guard_us(20);
  if (!timing->has_take_length_s()) timing->set_take_length_s(10);
  if (!timing->has_trigger_pulse_us()) timing->set_trigger_pulse_us(10);
  if (!timing->has_trigger_lead_slots()) timing->set_trigger_lead_slots(20);
  if (!timing->has_flicker_warn_modulation()) timing->set_flicker_warn_modulation(0);
  if (!timing->has_flicker_error_modulation()) timing->set_flicker_error_modulation(0.25);
  if (!timing->has_trigger_realtime_priority()) timing->set_trigger_realtime_priority(0);
  if (rig->pattern_set().empty()) rig->set_pattern_set(std::string(kFastage38));
  auto* sim = rig->mutable_sim();
  if (!sim->has_render_scale()) sim->set_render_scale(0.125);
  if (!sim->has_seed()) sim->set_seed(1);
  if (!sim->has_dome_radius_mm()) sim->set_dome_radius_mm(1000);
  if (!sim->has_cross_leakage()) sim->set_cross_leakage(0.01);
  if (!sim->has_cross_leakage_growth()) sim->set_cross_leakage_growth(0.05);
  if (!sim->has_full_on_electrons()) sim->set_full_on_electrons(4000);
  if (!sim->has_read_noise_e()) sim->set_read_noise_e(5);
  if (!sim->has_full_well_e()) sim->set_full_well_e(10000);
  if (!sim->has_supersample()) sim->set_supersample(1);
  auto* deviation = sim->mutable_camera_deviation();
  if (!deviation->has_scale()) deviation->set_scale(1);
  if (!deviation->has_position_mm()) deviation->set_position_mm(1.2);
  if (!deviation->has_rotation_deg()) deviation->set_rotation_deg(0.17);
  if (!deviation->has_focal()) deviation->set_focal(0.005);
  if (!deviation->has_principal_px()) deviation->set_principal_px(3);
  if (!deviation->has_radial()) deviation->set_radial(0.02);
  if (!deviation->has_radial2()) deviation->set_radial2(0.02);
  if (!deviation->has_tangential()) deviation->set_tangential(0.0003);
  auto* subject = sim->mutable_subject();
  if (subject->kind().empty()) subject->set_kind("head");
  if (subject->performance().empty()) subject->set_performance("default");
  if (!subject->has_head_resolution()) subject->set_head_resolution(256);
  if (!subject->has_size_mm()) subject->set_size_mm(subject->kind() == "plane" ? 300 : 100);
  if (subject->albedo().empty()) {
    for (double a : {0.6, 0.45, 0.35}) subject->add_albedo(a);
  }
  if (!subject->has_specular()) subject->set_specular(0.03);
  if (!subject->has_roughness()) subject->set_roughness(0.3);
  if (!subject->asset().neutral_obj().empty()) {
    auto* asset = subject->mutable_asset();
    if (!asset->has_specular_scale()) asset->set_specular_scale(0.1);
    if (!asset->has_units_mm()) asset->set_units_mm(1);
    if (asset->pivot_mm().empty()) {
      for (double p : {0.0, -95.0, -15.0}) asset->add_pivot_mm(p);
    }
  }
  if (subject->kind() == "charuco") {
    auto* board = subject->mutable_board();
    if (!board->has_squares_x()) board->set_squares_x(11);
    if (!board->has_squares_y()) board->set_squares_y(9);
    if (!board->has_square_mm()) board->set_square_mm(30);
    if (!board->has_marker_mm()) board->set_marker_mm(22);
    if (board->dictionary().empty()) board->set_dictionary("DICT_5X5_100");
    if (!board->has_pixels_per_mm()) board->set_pixels_per_mm(8);
  }
  if (!sim->has_texture_samples()) {
    sim->set_texture_samples(subject->kind() == "charuco" ? std::max<uint32_t>(4, sim->supersample())
                                                          : sim->supersample());
  }
  auto* storage = rig->mutable_storage();
  if (storage->root().empty()) storage->set_root("takes");
  if (!storage->has_host_write_mb_per_s()) storage->set_host_write_mb_per_s(2000);
  const bool fastage38 = rig->pattern_set() == kFastage38;

  for (auto& c : *rig->mutable_cameras()) {
    const bool hs = IsRoleHighSpeed(c);
    if (c.backend() == v1::CAMERA_BACKEND_UNSPECIFIED) c.set_backend(v1::CAMERA_BACKEND_SIM);
    if (c.pixel_format() == v1::PIXEL_FORMAT_UNSPECIFIED) c.set_pixel_format(v1::PIXEL_FORMAT_BAYER_RG8);
    if (!c.has_gain_db()) c.set_gain_db(0);
    if (!c.has_readout_us()) c.set_readout_us(0);
    auto* t = c.mutable_trigger();
    if (t->source() == v1::TRIGGER_SOURCE_UNSPECIFIED) t->set_source(v1::TRIGGER_SOURCE_HARDWARE_LINE);
    if (!t->has_divider() && (hs || fastage38)) t->set_divider(hs ? 1 : kFastage38Length);
    if (!t->has_slot_phase() && (hs || fastage38)) t->set_slot_phase(hs ? 0 : kFastage38ParallelFullOn);
    if (!c.has_frame_rate_hz()) {
      // The rate the schedule triggers it at: the slot clock divided. Free-running, a machine-vision camera's 24 fps.
      const bool triggered = t->source() != v1::TRIGGER_SOURCE_FREE_RUN && t->has_divider() && t->divider() >= 1;
      c.set_frame_rate_hz(triggered ? timing->slot_rate_hz() / static_cast<double>(t->divider())
                          : hs      ? timing->slot_rate_hz()
                                    : 24);
    }
    if (c.analyzer() == v1::ANALYZER_UNSPECIFIED) c.set_analyzer(v1::ANALYZER_LINEAR);
    if (c.link() == v1::LINK_KIND_UNSPECIFIED) c.set_link(hs ? v1::LINK_KIND_ON_CAMERA_RAM : v1::LINK_KIND_GIGE_10);
    if (!c.has_ram_gib()) c.set_ram_gib(0);
    if (!c.has_max_frame_rate_hz()) c.set_max_frame_rate_hz(0);
    if (!c.has_overlap_exposure_readout()) c.set_overlap_exposure_readout(true);
    if (!c.has_packet_size()) c.set_packet_size(1500);
    if (!c.has_frame_buffer_mib()) c.set_frame_buffer_mib(0);
    if (!c.has_offset_x()) c.set_offset_x(0);
    if (!c.has_offset_y()) c.set_offset_y(0);
    if (!c.has_binning()) c.set_binning(1);
    auto* g = c.mutable_gige();
    if (!g->has_buffers()) g->set_buffers(16);
    if (!g->has_packet_delay_ns()) g->set_packet_delay_ns(0);
    if (!g->has_ptp()) g->set_ptp(false);
    if (!g->has_packet_resend()) g->set_packet_resend(true);
    if (!g->has_reconnect_max_s()) g->set_reconnect_max_s(5);
    if (!g->has_packet_socket()) g->set_packet_socket(true);
    if (c.has_pose() && !c.pose().has_up()) c.mutable_pose()->mutable_up()->set_y(1);
    if (c.recording_host().empty()) c.set_recording_host(c.id());
  }
  for (auto& n : *rig->mutable_light_nodes()) {
    if (n.backend() == v1::LIGHT_BACKEND_UNSPECIFIED) n.set_backend(v1::LIGHT_BACKEND_SIM);
    if (n.has_unit_limits()) ApplyLimitDefaults(n.mutable_unit_limits());
    if (n.has_sim() && !n.sim().has_extra_delay_us()) n.mutable_sim()->set_extra_delay_us(0);
    if (n.has_modbus()) {
      auto* m = n.mutable_modbus();
      if (!m->has_unit_id()) m->set_unit_id(1);
      if (!m->has_timeout_ms()) m->set_timeout_ms(100);
      if (!m->has_retries()) m->set_retries(2);
      if (m->has_tcp() && !m->tcp().has_port()) m->mutable_tcp()->set_port(502);
      if (m->has_rtu()) {
        auto* rtu = m->mutable_rtu();
        if (!rtu->has_baud()) rtu->set_baud(115200);
        if (rtu->parity().empty()) rtu->set_parity("N");
        if (!rtu->has_data_bits()) rtu->set_data_bits(8);
        if (!rtu->has_stop_bits()) rtu->set_stop_bits(1);
      }
    }
    for (auto& u : *n.mutable_units()) {
      if (!u.has_intensity_scale()) u.set_intensity_scale(1.0);
      if (u.has_limits()) ApplyLimitDefaults(u.mutable_limits());
    }
  }
  for (auto& w : *rig->mutable_processing_workers()) {
    if (!w.has_threads()) w.set_threads(0);
  }
}

std::vector<RigError> ValidateRig(const RigConfig& rig, absl::string_view base_dir,
                                  const RigValidationOptions& options) {
  Checker check;
  check.Id("stage.id", rig.stage().id());

  const auto& controller = rig.controller();
  std::string listen_host;
  int listen_port;
  if (absl::Status s = ParseHostPort(controller.listen(), &listen_host, &listen_port); !s.ok()) {
    check.Add("controller.listen", std::string(s.message()));
  }
  check.InRange("controller.health_poll_interval_ms", controller.health_poll_interval_ms(), 10, 60000);
  check.InRange("controller.health_timeout_ms", controller.health_timeout_ms(), 10, 60000);
  check.InRange("controller.clock_sync_interval_ms", controller.clock_sync_interval_ms(), 50, 600000);
  check.InRange("controller.clock_sync_burst", controller.clock_sync_burst(), 1, 64);
  check.InRange("controller.take_stall_s", controller.take_stall_s(), 0, 86400);

  const auto& timing = rig.timing();
  check.InRange("timing.slot_rate_hz", timing.slot_rate_hz(), 1, 100000);
  check.InRange("timing.led_switch_delay_us", timing.led_switch_delay_us(), 0, 1e6);
  check.InRange("timing.led_settle_us", timing.led_settle_us(), 0, 1e6);
  check.InRange("timing.exposure_guard_us", timing.exposure_guard_us(), 0, 1e6);
  if (timing.slot_rate_hz() != std::floor(timing.slot_rate_hz())) {
    check.Add("timing.slot_rate_hz", absl::StrFormat("%g is not a whole number of slots per second (the schedule "
                                                     "keeps exact integer ticks of 1/lcm(rate, 10^9) s)",
                                                     timing.slot_rate_hz()));
  }
  check.InRange("timing.take_length_s", timing.take_length_s(), 1e-3, 86400.0 * 7);
  if (timing.slot_rate_hz() >= 1 && timing.slot_rate_hz() <= 100000 &&
      timing.slot_rate_hz() == std::floor(timing.slot_rate_hz())) {
    // The schedule counts time in ticks of 1/lcm(rate, 10^9) s in 64 bits; a take must fit (with room to spare).
    const double ticks_per_second =
        static_cast<double>(std::lcm<int64_t>(static_cast<int64_t>(timing.slot_rate_hz()), 1'000'000'000));
    const double max_take_s = 4.0e18 / ticks_per_second;
    if (timing.take_length_s() > max_take_s) {
      check.Add("timing.take_length_s",
                absl::StrFormat("%g s does not fit the exact time base at %g slots/s (ticks of 1/%.0f s); at most "
                                "%.0f s at this rate",
                                timing.take_length_s(), timing.slot_rate_hz(), ticks_per_second, max_take_s));
    }
  }
  check.InRange("timing.trigger_pulse_us", timing.trigger_pulse_us(), 0.001, 1e6);
  check.InRange("timing.trigger_lead_slots", timing.trigger_lead_slots(), 1, 100000);
  check.InRange("timing.flicker_warn_modulation", timing.flicker_warn_modulation(), 0, 10);
  check.InRange("timing.flicker_error_modulation", timing.flicker_error_modulation(), 0, 10);
  check.InRange("timing.trigger_realtime_priority", timing.trigger_realtime_priority(), 0, 99);

  const v1::SecurityConfig& security = rig.security();
  check.InRange("security.reload_interval_s", security.reload_interval_s(), 1, 3600);
  if (security.transport() == v1::TRANSPORT_MODE_MUTUAL_TLS) {
    for (const auto& [field, value] : {std::pair{"ca_file", security.ca_file()}, {"cert_dir", security.cert_dir()}}) {
      if (value.empty()) check.Add(absl::StrCat("security.", field), "mutual TLS needs it");
    }
  } else if (!security.ca_file().empty() || !security.cert_dir().empty()) {
    check.Add("security.transport", "ca_file and cert_dir are set, but the transport is plain text (set MUTUAL_TLS)");
  }
  if (!IsBuiltinPatternSet(rig.pattern_set())) {
    std::filesystem::path p(rig.pattern_set());
    if (p.is_relative()) p = std::filesystem::path(std::string(base_dir)) / p;
    std::error_code ec;
    if (!std::filesystem::is_regular_file(p, ec)) {
      check.Add("pattern_set", absl::StrCat("\"", rig.pattern_set(), "\" is neither a built-in pattern set (",
                                            kFastage38, ") nor a readable file (looked for ", p.string(), ")"));
    }
  }
  if (rig.storage().root().empty()) check.Add("storage.root", "required field is missing");
  if (!(rig.sim().render_scale() > 0 && rig.sim().render_scale() <= 1)) {
    check.Add("sim.render_scale", absl::StrFormat("%g is not in (0, 1]", rig.sim().render_scale()));
  }
  check.InRange("sim.dome_radius_mm", rig.sim().dome_radius_mm(), 100, 100000);
  check.InRange("sim.cross_leakage", rig.sim().cross_leakage(), 0, 1);
  check.InRange("sim.cross_leakage_growth", rig.sim().cross_leakage_growth(), 0, 1);
  check.InRange("sim.full_on_electrons", rig.sim().full_on_electrons(), 1, 1e7);
  check.InRange("sim.read_noise_e", rig.sim().read_noise_e(), 0, 1000);
  check.InRange("sim.full_well_e", rig.sim().full_well_e(), 1, 1e7);
  check.InRange("sim.supersample", rig.sim().supersample(), 1, 8);
  check.InRange("sim.texture_samples", rig.sim().texture_samples(), std::max<uint32_t>(1, rig.sim().supersample()), 16);
  {
    const v1::SimCameraDeviation& d = rig.sim().camera_deviation();
    check.InRange("sim.camera_deviation.scale", d.scale(), 0, 100);
    check.InRange("sim.camera_deviation.position_mm", d.position_mm(), 0, 100);
    check.InRange("sim.camera_deviation.rotation_deg", d.rotation_deg(), 0, 10);
    check.InRange("sim.camera_deviation.focal", d.focal(), 0, 0.2);
    check.InRange("sim.camera_deviation.principal_px", d.principal_px(), 0, 1000);
    check.InRange("sim.camera_deviation.radial", d.radial(), 0, 1);
    check.InRange("sim.camera_deviation.radial2", d.radial2(), 0, 1);
    check.InRange("sim.camera_deviation.tangential", d.tangential(), 0, 0.1);
  }
  {
    const v1::SimSubject& subject = rig.sim().subject();
    if (subject.kind() != "head" && subject.kind() != "sphere" && subject.kind() != "plane" &&
        subject.kind() != "charuco") {
      check.Add("sim.subject.kind",
                absl::StrCat("\"", subject.kind(), "\" is not a subject kind (head, sphere, plane, charuco)"));
    }
    if (!subject.asset().neutral_obj().empty()) {
      const v1::SimHeadAsset& asset = subject.asset();
      if (subject.kind() != "head") check.Add("sim.subject.asset", "is a head: needs kind \"head\"");
      if (asset.albedo().empty()) check.Add("sim.subject.asset.albedo", "is required with a neutral_obj");
      check.InRange("sim.subject.asset.specular_scale", asset.specular_scale(), 0, 100);
      check.InRange("sim.subject.asset.units_mm", asset.units_mm(), 1e-6, 1e6);
      if (asset.pivot_mm_size() != 3) {
        check.Add("sim.subject.asset.pivot_mm", absl::StrCat("needs 3 values (x, y, z), has ", asset.pivot_mm_size()));
      }
    } else if (subject.asset().ByteSizeLong() != 0) {
      check.Add("sim.subject.asset.neutral_obj", "is required when an asset is given");
    }
    if (subject.kind() == "charuco") {
      const v1::SimBoard& board = subject.board();
      check.InRange("sim.subject.board.squares_x", board.squares_x(), 2, 100);
      check.InRange("sim.subject.board.squares_y", board.squares_y(), 2, 100);
      check.InRange("sim.subject.board.square_mm", board.square_mm(), 1, 1000);
      check.InRange("sim.subject.board.marker_mm", board.marker_mm(), 0.5, 1000);
      if (board.marker_mm() >= board.square_mm()) {
        check.Add("sim.subject.board.marker_mm",
                  absl::StrCat(board.marker_mm(), " must be smaller than square_mm (", board.square_mm(), ")"));
      }
      check.InRange("sim.subject.board.pixels_per_mm", board.pixels_per_mm(), 0.5, 100);
    }
    check.InRange("sim.subject.head_resolution", subject.head_resolution(), 16, 4096);
    check.InRange("sim.subject.blood_flow", subject.blood_flow(), 0.0, 1.0);
    if (subject.blood_flow() != 0 && (subject.kind() != "head" || !subject.asset().neutral_obj().empty())) {
      check.Add("sim.subject.blood_flow",
                "flushes the procedural head's skin: it needs kind \"head\" without an asset");
    }
    if (subject.identity() != 0 && (subject.kind() != "head" || !subject.asset().neutral_obj().empty())) {
      check.Add("sim.subject.identity",
                "draws the procedural head's proportions: it needs kind \"head\" without an asset");
    }
    check.InRange("sim.subject.size_mm", subject.size_mm(), 1, 2000);
    if (subject.albedo_size() != 3) {
      check.Add("sim.subject.albedo", absl::StrCat("needs 3 values (linear R, G, B), has ", subject.albedo_size()));
    }
    for (int i = 0; i < subject.albedo_size(); ++i) {
      check.InRange(absl::StrCat("sim.subject.albedo[", i, "]"), subject.albedo(i), 0, 1);
    }
    check.InRange("sim.subject.specular", subject.specular(), 0, 1);
    check.InRange("sim.subject.roughness", subject.roughness(), 0.001, 1);
  }
  {
    std::set<std::string> units, lights, cameras;
    for (const auto& n : rig.light_nodes()) {
      lights.insert(n.id());
      for (const auto& u : n.units()) units.insert(u.id());
    }
    for (const auto& c : rig.cameras()) cameras.insert(c.id());
    if (rig.sim().gige_fakes()) {
      // Each fake listens at its camera's address: GigE Vision's control port is fixed, so one camera per address.
      std::map<std::string, std::string> by_address;
      for (const auto& c : rig.cameras()) {
        if (c.backend() != v1::CAMERA_BACKEND_ARAVIS) continue;
        in_addr a{};
        if (inet_pton(AF_INET, c.device().c_str(), &a) != 1) {
          check.Add(absl::StrCat("cameras[", c.id(), "].device"),
                    absl::StrCat("\"", c.device(),
                                 "\" is not an IPv4 address; with sim.gige_fakes the fake camera "
                                 "listens at its camera's device address (e.g. 127.0.0.11)"));
        } else if (auto [it, fresh] = by_address.emplace(c.device(), c.id()); !fresh) {
          check.Add(absl::StrCat("cameras[", c.id(), "].device"),
                    absl::StrCat(c.device(), " is camera ", it->second, "'s too: one fake camera per address"));
        }
      }
    }
    for (int i = 0; i < rig.sim().faults_size(); ++i) {
      const v1::SimFault& f = rig.sim().faults(i);
      const std::string p = absl::StrCat("sim.faults[", i, "]");
      const bool unit = units.count(f.target()) > 0, light = lights.count(f.target()) > 0,
                 camera = cameras.count(f.target()) > 0;
      if (!unit && !light && !camera) {
        check.Add(p + ".target", absl::StrCat("\"", f.target(), "\" is no LED unit, light node or camera of the rig"));
        continue;
      }
      if (f.dead() && !unit) check.Add(p + ".dead", "only an LED unit can be dead");
      if (f.has_delay_us() && camera) check.Add(p + ".delay_us", "applies to an LED unit or a light node");
      if ((f.has_miss_triggers() || f.has_drop_frames() || f.has_clock_offset_us() || f.has_clock_drift_ppm()) &&
          !camera) {
        check.Add(p, "miss_triggers, drop_frames and the clock apply to a camera");
      }
      if (f.has_crash_at_s() && unit) check.Add(p + ".crash_at_s", "applies to a light node or a camera");
      if (f.drop_slots_size() > 0 && !camera) check.Add(p + ".drop_slots", "applies to a camera");
      if (f.has_extra_steps() && !light) check.Add(p + ".extra_steps", "applies to a light node");
      if (f.has_extra_steps()) check.InRange(p + ".extra_steps", f.extra_steps(), 0, 1000);
      for (int k = 0; k < f.drop_slots_size(); ++k) {
        if (f.drop_slots(k) < 0) check.Add(absl::StrCat(p, ".drop_slots[", k, "]"), "must be >= 0");
      }
      if (f.has_delay_us()) check.InRange(p + ".delay_us", f.delay_us(), 0, 1e6);
      if (f.has_miss_triggers()) check.InRange(p + ".miss_triggers", f.miss_triggers(), 0, 1);
      if (f.has_drop_frames()) check.InRange(p + ".drop_frames", f.drop_frames(), 0, 1);
      if (f.has_clock_drift_ppm()) check.InRange(p + ".clock_drift_ppm", f.clock_drift_ppm(), -1e4, 1e4);
      if (f.has_crash_at_s()) check.InRange(p + ".crash_at_s", f.crash_at_s(), 0, 1e6);
      if (f.has_packet_loss() || f.has_link_down_at_s() || f.has_link_down_s()) {
        const auto* c = camera ? &*std::find_if(rig.cameras().begin(), rig.cameras().end(),
                                                [&](const v1::CameraConfig& cc) { return cc.id() == f.target(); })
                               : nullptr;
        if (c == nullptr || !rig.sim().gige_fakes() || c->backend() != v1::CAMERA_BACKEND_ARAVIS) {
          check.Add(p, "packet_loss and link_down apply to a fake GigE Vision camera (sim.gige_fakes, backend aravis)");
        }
      }
      if (f.has_packet_loss()) check.InRange(p + ".packet_loss", f.packet_loss(), 0, 1);
      if (f.has_link_down_at_s()) check.InRange(p + ".link_down_at_s", f.link_down_at_s(), 0, 1e6);
      if (f.has_link_down_s()) check.InRange(p + ".link_down_s", f.link_down_s(), 0, 3600);
      if (f.has_link_down_at_s() != f.has_link_down_s()) {
        check.Add(p, "link_down_at_s and link_down_s come together");
      }
      if (f.has_board_silent_at_s() || f.has_board_silent_s()) {
        const auto* n = light ? &*std::find_if(rig.light_nodes().begin(), rig.light_nodes().end(),
                                               [&](const v1::LightNodeConfig& nn) { return nn.id() == f.target(); })
                              : nullptr;
        if (n == nullptr || !rig.sim().modbus_fakes() || n->backend() != v1::LIGHT_BACKEND_MODBUS) {
          check.Add(p, "board_silent applies to a fake LED board (sim.modbus_fakes, a light node with backend modbus)");
        }
        if (f.has_board_silent_at_s() != f.has_board_silent_s()) {
          check.Add(p, "board_silent_at_s and board_silent_s come together");
        }
      }
      if (f.has_crash_at_s() && light && rig.sim().modbus_fakes()) {
        const auto& n = *std::find_if(rig.light_nodes().begin(), rig.light_nodes().end(),
                                      [&](const v1::LightNodeConfig& nn) { return nn.id() == f.target(); });
        if (n.backend() == v1::LIGHT_BACKEND_MODBUS) {
          check.Add(p + ".crash_at_s",
                    "a light node on a fake LED board (sim.modbus_fakes) does not crash with the "
                    "world; use board_silent_at_s, or stop its process");
        }
      }
      if (f.has_board_silent_at_s()) check.InRange(p + ".board_silent_at_s", f.board_silent_at_s(), 0, 1e6);
      if (f.has_board_silent_s()) check.InRange(p + ".board_silent_s", f.board_silent_s(), 0, 3600);
    }
  }
  check.Positive("storage.host_write_mb_per_s", rig.storage().host_write_mb_per_s());

  // Node ids share one namespace: the controller, stagectl and the logs address nodes by id alone.
  std::map<std::string, std::string> node_ids;  // id -> path of its first definition
  auto check_unique = [&](const std::string& path, const std::string& id) {
    if (id.empty()) return;
    auto [it, inserted] = node_ids.emplace(id, path);
    if (!inserted) check.Add(path, absl::StrCat("duplicate node id \"", id, "\" (also ", it->second, ")"));
  };

  for (int i = 0; i < rig.cameras_size(); ++i) {
    std::string p = absl::StrCat("cameras[", i, "]");
    CheckCamera(check, p, rig.cameras(i), options);
    check_unique(p + ".id", rig.cameras(i).id());
  }
  std::map<std::string, std::string> unit_ids;
  for (int i = 0; i < rig.light_nodes_size(); ++i) {
    std::string p = absl::StrCat("light_nodes[", i, "]");
    CheckLightNode(check, p, rig.light_nodes(i), options, &unit_ids);
    check_unique(p + ".id", rig.light_nodes(i).id());
  }
  for (int i = 0; i < rig.processing_workers_size(); ++i) {
    std::string p = absl::StrCat("processing_workers[", i, "]");
    const auto& w = rig.processing_workers(i);
    check.Id(p + ".id", w.id());
    check_unique(p + ".id", w.id());
    CheckAddress(check, p + ".address", w.address(), options.require_addresses);
    check.InRange(p + ".threads", w.threads(), 0, 1024);
  }

  if (!timing.sync_generator().empty()) {
    const LightNodeConfig* generator = nullptr;
    for (const auto& n : rig.light_nodes()) {
      if (n.id() == timing.sync_generator()) generator = &n;
    }
    if (generator == nullptr) {
      std::vector<std::string> ids;
      for (const auto& n : rig.light_nodes()) ids.push_back(n.id());
      check.Add("timing.sync_generator",
                absl::StrCat("light node \"", timing.sync_generator(),
                             "\" is not defined (light nodes: ", ids.empty() ? "none" : absl::StrJoin(ids, ", "), ")"));
    } else if (!generator->has_gpiod() || !generator->gpiod().drives_slot_clock()) {
      check.Add("timing.sync_generator", absl::StrCat("light node \"", generator->id(),
                                                      "\" cannot generate the slot clock: it needs backend gpiod with "
                                                      "gpiod.drives_slot_clock: true"));
    }
  }
  if (!timing.clock_witness().empty()) {
    const LightNodeConfig* witness = nullptr;
    for (const auto& n : rig.light_nodes()) {
      if (n.id() == timing.clock_witness()) witness = &n;
    }
    if (!timing.sync_generator().empty()) {
      check.Add("timing.clock_witness", absl::StrCat("is set, but timing.sync_generator (\"", timing.sync_generator(),
                                                     "\") drives the clock: a witness is for an external generator"));
    } else if (witness == nullptr) {
      check.Add("timing.clock_witness", absl::StrCat("light node \"", timing.clock_witness(), "\" is not defined"));
    } else if (witness->backend() == v1::LIGHT_BACKEND_MODBUS) {
      check.Add("timing.clock_witness", absl::StrCat("light node \"", witness->id(),
                                                     "\" cannot timestamp the slot clock: its Modbus board steps on "
                                                     "the edges out of its sight (use a gpiod node)"));
    }
  }
  // One line, one driver: only the sync generator drives the slot clock.
  for (int i = 0; i < rig.light_nodes_size(); ++i) {
    const LightNodeConfig& n = rig.light_nodes(i);
    if (n.has_gpiod() && n.gpiod().drives_slot_clock() && n.id() != timing.sync_generator()) {
      check.Add(absl::StrCat("light_nodes[", i, "].gpiod.drives_slot_clock"),
                absl::StrCat("light node \"", n.id(), "\" drives the slot clock but is not timing.sync_generator (\"",
                             timing.sync_generator(), "\")"));
    }
  }
  return check.Take();
}

absl::StatusOr<LoadedRig> LoadRigFromText(absl::string_view text, absl::string_view source_name,
                                          absl::string_view base_dir, const RigValidationOptions& options,
                                          std::vector<std::string>* all_errors) {
  LoadedRig loaded;
  loaded.source_name = std::string(source_name);
  loaded.base_dir = std::string(base_dir);
  absl::Status parsed = ParseYamlToProto(text, source_name, &loaded.rig, &loaded.source_map);
  if (!parsed.ok()) {
    if (all_errors != nullptr) all_errors->push_back(std::string(parsed.message()));
    return parsed;
  }
  loaded.as_written = loaded.rig;
  ApplyRigDefaults(&loaded.rig);
  std::vector<RigError> errors = ValidateRig(loaded.rig, base_dir, options);
  if (errors.empty()) return loaded;
  std::vector<std::string> formatted;
  for (const RigError& e : errors) {
    formatted.push_back(FormatConfigError(source_name, loaded.source_map.Find(e.path), e.path, e.message));
  }
  std::string message = formatted.front();
  if (formatted.size() > 1) absl::StrAppend(&message, " (and ", formatted.size() - 1, " more errors)");
  if (all_errors != nullptr) *all_errors = std::move(formatted);
  return absl::InvalidArgumentError(message);
}

absl::StatusOr<LoadedRig> LoadRig(absl::string_view path, const RigValidationOptions& options,
                                  std::vector<std::string>* all_errors) {
  if (path == kBuiltinRigName) {
    return LoadRigFromText(BuiltinRigText(), "fastage.yaml (built in)", ".", options, all_errors);
  }
  std::string file(path);
  std::error_code ec;
  if (std::filesystem::is_directory(file, ec)) {
    return absl::InvalidArgumentError(absl::StrCat(file, ": is a directory, not a rig file"));
  }
  STAGE_ASSIGN_OR_RETURN(std::string text, ReadFileToString(file, "rig file"));
  std::filesystem::path parent = std::filesystem::path(file).parent_path();
  std::string base_dir = parent.empty() ? std::string(".") : parent.string();
  return LoadRigFromText(text, file, base_dir, options, all_errors);
}

std::string RigHash(const RigConfig& rig) {
  RigConfig copy = rig;
  for (auto& c : *copy.mutable_cameras()) c.clear_address();
  for (auto& n : *copy.mutable_light_nodes()) n.clear_address();
  for (auto& w : *copy.mutable_processing_workers()) w.clear_address();
  return StableHash(copy);
}

std::string CameraRoleName(v1::CameraRole role) {
  return role == v1::CAMERA_ROLE_HIGH_SPEED ? "high-speed" : "machine-vision";
}

std::string PixelFormatName(v1::PixelFormat format) {
  switch (format) {
    case v1::PIXEL_FORMAT_MONO8:
      return "Mono8";
    case v1::PIXEL_FORMAT_MONO12:
      return "Mono12";
    case v1::PIXEL_FORMAT_MONO16:
      return "Mono16";
    case v1::PIXEL_FORMAT_BAYER_RG8:
      return "BayerRG8";
    case v1::PIXEL_FORMAT_BAYER_GR8:
      return "BayerGR8";
    case v1::PIXEL_FORMAT_BAYER_GB8:
      return "BayerGB8";
    case v1::PIXEL_FORMAT_BAYER_BG8:
      return "BayerBG8";
    case v1::PIXEL_FORMAT_BAYER_RG12:
      return "BayerRG12";
    case v1::PIXEL_FORMAT_BAYER_RG16:
      return "BayerRG16";
    case v1::PIXEL_FORMAT_RGB8:
      return "RGB8";
    default:
      return "";
  }
}

std::string StableHash(const google::protobuf::Message& message) {
  std::string bytes;
  {
    google::protobuf::io::StringOutputStream stream(&bytes);
    google::protobuf::io::CodedOutputStream coded(&stream);
    coded.SetSerializationDeterministic(true);
    message.SerializeToCodedStream(&coded);
  }
  return absl::StrFormat("%016x", Fnv1a64(bytes));
}

uint64_t Fnv1a64(absl::string_view bytes, uint64_t basis) {
  uint64_t h = basis;
  for (unsigned char c : bytes) {
    h ^= c;
    h *= 1099511628211ull;
  }
  return h;
}

namespace {

template <typename T>
absl::StatusOr<const T*> FindNode(const google::protobuf::RepeatedPtrField<T>& nodes, const LoadedRig& loaded,
                                  absl::string_view id, absl::string_view what) {
  std::vector<std::string> ids;
  for (const T& n : nodes) {
    if (n.id() == id) return &n;
    ids.push_back(n.id());
  }
  return absl::NotFoundError(absl::StrCat(what, " \"", id, "\" is not in ", loaded.source_name, " (", what,
                                          "s: ", ids.empty() ? "none" : absl::StrJoin(ids, ", "), ")"));
}

}  // namespace

absl::StatusOr<const v1::CameraConfig*> FindCamera(const LoadedRig& loaded, absl::string_view id) {
  return FindNode(loaded.rig.cameras(), loaded, id, "camera");
}

absl::StatusOr<const v1::LightNodeConfig*> FindLightNode(const LoadedRig& loaded, absl::string_view id) {
  return FindNode(loaded.rig.light_nodes(), loaded, id, "light node");
}

absl::StatusOr<const v1::ProcessingWorkerConfig*> FindProcessingWorker(const LoadedRig& loaded, absl::string_view id) {
  return FindNode(loaded.rig.processing_workers(), loaded, id, "processing worker");
}

std::string DefaultCacheDir() {
  if (const char* dir = std::getenv("FASTAGE_CACHE_DIR"); dir != nullptr && *dir != '\0') return dir;
  // On disk, not in a tmpfs such as $XDG_RUNTIME_DIR: a cache file would hold memory there besides the page cache.
  if (const char* xdg = std::getenv("XDG_CACHE_HOME"); xdg != nullptr && *xdg != '\0') {
    return absl::StrCat(xdg, "/fastage");
  }
  if (const char* home = std::getenv("HOME"); home != nullptr && *home != '\0') {
    return absl::StrCat(home, "/.cache/fastage");
  }
  return absl::StrCat("/tmp/fastage-", getuid(), "/cache");
}

std::string DefaultSimRunDir() {
  if (const char* xdg = std::getenv("XDG_RUNTIME_DIR"); xdg != nullptr && *xdg != '\0') {
    return absl::StrCat(xdg, "/fastage/stage-sim");
  }
  return absl::StrCat("/tmp/fastage-", getuid(), "/stage-sim");
}

}  // namespace stage
