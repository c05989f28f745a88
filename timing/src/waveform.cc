// VCD and SVG export of a schedule's planned signals.
#include "stage/timing/waveform.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <set>

#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_replace.h"
#include "absl/strings/str_split.h"
#include "stage/common/version.h"
#include "stage/timing/schedule.h"
#include "stage/timing/time_base.h"
#include "stage/timing/verifier.h"

namespace stage::timing {
namespace {

using Interval = std::pair<int64_t, int64_t>;

int64_t FloorDiv(int64_t a, int64_t b) {
  int64_t q = a / b;
  if ((a % b != 0) && ((a < 0) != (b < 0))) --q;
  return q;
}

// Sorts, drops empty intervals and unites overlapping or touching ones.
std::vector<Interval> Merge(std::vector<Interval> v) {
  std::sort(v.begin(), v.end());
  std::vector<Interval> out;
  for (const Interval& i : v) {
    if (i.second <= i.first) continue;
    if (!out.empty() && i.first <= out.back().second) {
      out.back().second = std::max(out.back().second, i.second);
    } else {
      out.push_back(i);
    }
  }
  return out;
}

// Adds [origin + n * period + offset, + length) for every n whose interval meets [w0, w1), clipped.
void AddSequence(std::vector<Interval>* out, int64_t origin, int64_t period, int64_t offset, int64_t length, int64_t w0,
                 int64_t w1) {
  if (length <= 0 || period <= 0) return;
  const int64_t n_min = FloorDiv(w0 - origin - offset - length, period);
  const int64_t n_max = FloorDiv(w1 - origin - offset, period) + 1;
  for (int64_t n = n_min; n <= n_max; ++n) {
    const int64_t a = std::max(w0, origin + n * period + offset);
    const int64_t b = std::min(w1, origin + n * period + offset + length);
    if (b > a) out->push_back({a, b});
  }
}

int PatternBits(int64_t n) {
  int bits = 1;
  while ((int64_t{1} << bits) < n) ++bits;
  return bits;
}

std::string XmlEscape(absl::string_view s) {
  return absl::StrReplaceAll(s, {{"&", "&amp;"}, {"<", "&lt;"}, {">", "&gt;"}, {"\"", "&quot;"}});
}

}  // namespace

std::vector<Signal> PlannedSignals(const v1::Schedule& schedule, const WaveformWindow& window) {
  const TimeBase base = TimeBase::FromProto(schedule.time_base());
  const int64_t T = base.ticks_per_slot();
  const int64_t n = CycleLength(schedule);
  const int64_t w0 = base.SlotStartTicks(window.first_slot);
  const int64_t w1 = base.SlotStartTicks(window.first_slot + window.slot_count);
  std::vector<Signal> signals;
  auto add = [&](std::string name, std::string scope, std::string description, std::vector<Interval> high) {
    signals.push_back({std::move(name), std::move(scope), std::move(description), Merge(std::move(high))});
  };

  std::vector<Interval> v;
  AddSequence(&v, 0, T, 0, T / 2, w0, w1);
  add("slot_clock", "clocks", "slot clock: rises at every slot edge, 50 % duty", std::move(v));
  v.clear();
  AddSequence(&v, 0, n * T, 0, T / 2, w0, w1);
  add("cycle_start", "clocks", absl::StrCat("first slot of each ", n, "-pattern cycle (frame clock)"), std::move(v));
  std::set<std::pair<uint32_t, uint32_t>> divided;
  for (const auto& c : schedule.cameras()) {
    if (c.divider() > 1 && c.source() == v1::TRIGGER_SOURCE_HARDWARE_LINE)
      divided.insert({c.divider(), c.slot_phase()});
  }
  for (const auto& [d, p] : divided) {
    v.clear();
    AddSequence(&v, base.SlotStartTicks(p), d * T, 0, T / 2, w0, w1);
    add(absl::StrCat("clock_div", d, "_phase", p), "clocks",
        absl::StrCat("slot clock divided by ", d, ", phase ", p,
                     " (hardware trigger line of cameras with that divider)"),
        std::move(v));
  }
  // Most significant bit first: GTKWave joins bits declared in this order into pattern_id[5:0].
  const int bits = PatternBits(n);
  for (int b = bits - 1; b >= 0; --b) {
    v.clear();
    for (int64_t p = 0; p < n; ++p) {
      if ((p >> b) & 1) AddSequence(&v, base.SlotStartTicks(p), n * T, 0, T, w0, w1);
    }
    add(absl::StrCat("pattern_id[", b, "]"), "pattern",
        absl::StrCat("bit ", b, " of the pattern index of the slot (", bits, "-bit bus; [0] is the LSB)"),
        std::move(v));
  }
  v.clear();
  AddSequence(&v, 0, T, schedule.steady_start_ticks(),
              schedule.steady_end_ticks() - schedule.guard_ticks() - schedule.steady_start_ticks(), w0, w1);
  add("steady_window", "pattern",
      "where an exposure may be: light steady on every node, until the next switch less the guard", std::move(v));
  for (const auto& node : schedule.light_nodes()) {
    v.clear();
    AddSequence(&v, 0, T, node.switch_ticks(), node.steady_start_ticks() - node.switch_ticks(), w0, w1);
    add(node.id() + "_step", "lights/" + node.id(),
        absl::StrCat("light node ", node.id(), " stepping: from its switch until its light is steady"), std::move(v));
  }
  for (const auto& c : schedule.cameras()) {
    const int64_t origin = base.SlotStartTicks(c.slot_phase());
    const std::string scope = "cameras/" + c.id();
    v.clear();
    AddSequence(&v, origin, c.period_ticks(), c.trigger_ticks(), c.trigger_pulse_ticks(), w0, w1);
    add(c.id() + "_trigger", scope, absl::StrCat("camera ", c.id(), " trigger pulse"), std::move(v));
    v.clear();
    AddSequence(&v, origin, c.period_ticks(), c.trigger_ticks(), c.exposure_ticks(), w0, w1);
    add(c.id() + "_exposure", scope, absl::StrCat("camera ", c.id(), " exposure active"), std::move(v));
    v.clear();
    AddSequence(&v, origin, c.period_ticks(), c.trigger_ticks() + c.exposure_ticks(), c.readout_ticks(), w0, w1);
    add(c.id() + "_readout", scope,
        absl::StrCat("camera ", c.id(), " sensor readout",
                     c.readout_declared() ? "" : " (assumed: rest of the period)"),
        std::move(v));
  }
  return signals;
}

std::string VcdName(absl::string_view name) {
  std::string out;
  for (char c : name) {
    if (c == '[') {
      absl::StrAppend(&out, name.substr(out.size()));
      break;
    }
    out.push_back(absl::ascii_isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '$' ? c : '_');
  }
  if (!out.empty() && absl::ascii_isdigit(static_cast<unsigned char>(out[0]))) out.insert(out.begin(), '_');
  return out;
}

absl::StatusOr<std::string> TimescaleName(int64_t timescale_fs) {
  static const char* kUnits[] = {"fs", "ps", "ns", "us", "ms", "s"};
  int64_t unit = 1;
  for (const char* name : kUnits) {
    for (int64_t mult : {1, 10, 100}) {
      if (unit * mult == timescale_fs) return absl::StrCat(mult, " ", name);
    }
    unit *= 1000;
  }
  return absl::InvalidArgumentError(
      absl::StrCat("timescale ", timescale_fs, " fs is not 1, 10 or 100 fs, ps, ns, us, ms or s"));
}

absl::StatusOr<int64_t> ParseTimescale(const std::string& text) {
  std::string t = absl::AsciiStrToLower(absl::StrReplaceAll(text, {{" ", ""}}));
  size_t digits = 0;
  while (digits < t.size() && absl::ascii_isdigit(static_cast<unsigned char>(t[digits]))) ++digits;
  int64_t mult = 0;
  const std::map<std::string, int64_t> units = {{"fs", 1},          {"ps", 1000},          {"ns", 1000000},
                                                {"us", 1000000000}, {"ms", 1000000000000}, {"s", 1000000000000000}};
  auto unit = units.find(t.substr(digits));
  if (digits > 0 && absl::SimpleAtoi(t.substr(0, digits), &mult) && unit != units.end() &&
      (mult == 1 || mult == 10 || mult == 100)) {
    return mult * unit->second;
  }
  return absl::InvalidArgumentError(
      absl::StrCat("timescale \"", text, "\" is not 1, 10 or 100 followed by fs, ps, ns, us, ms or s (e.g. 1ns)"));
}

absl::StatusOr<std::string> ScheduleToVcd(const v1::Schedule& schedule, const WaveformWindow& window,
                                          const VcdOptions& options) {
  if (window.slot_count <= 0) return absl::InvalidArgumentError("the waveform window has no slots");
  auto timescale = TimescaleName(options.timescale_fs);
  if (!timescale.ok()) return timescale.status();
  const TimeBase base = TimeBase::FromProto(schedule.time_base());
  const std::vector<Signal> signals = PlannedSignals(schedule, window);
  const int64_t u0 = base.TicksToUnits(base.SlotStartTicks(window.first_slot), options.timescale_fs);
  const int64_t u1 =
      base.TicksToUnits(base.SlotStartTicks(window.first_slot + window.slot_count), options.timescale_fs);

  // Identifier codes: printable ASCII 33..126, base 94.
  auto code = [](size_t i) {
    std::string s;
    do {
      s.push_back(static_cast<char>(33 + i % 94));
      i /= 94;
    } while (i > 0);
    return s;
  };

  std::string out;
  absl::StrAppend(&out, "$date\n  (not recorded: the same schedule always writes the same file)\n$end\n");
  absl::StrAppend(&out, "$version\n  FaStage ", kVersion, " schedule export\n$end\n");
  absl::StrAppend(
      &out, "$comment\n  schedule ", schedule.hash(), ", pattern set ", schedule.pattern_set(), ", ",
      schedule.time_base().slot_rate_hz(), " slots/s\n  slots ", window.first_slot, " to ",
      window.first_slot + window.slot_count - 1, "; time 0 is the edge of slot 0\n",
      "  exact times are integer ticks of 1/", schedule.time_base().ticks_per_second(),
      " s; each edge is rounded on its own to the nearest ", *timescale, ", so edges are exact to half\n",
      "  a unit and never drift. Buses are written bit by bit, most significant first (pattern_id[0] is the\n",
      "  LSB): GTKWave joins them into one bus, and readers that take only one-bit wires (libsigrok 0.5)\n",
      "  read them too.\n");
  // VCD names: identifiers, unique (ids that differ only in '-' vs '_' get a suffix).
  std::vector<std::string> vcd_names;
  std::set<std::string> used;
  for (const Signal& signal : signals) {
    std::string name = VcdName(signal.name);
    for (int n = 2; !used.insert(name).second; ++n) name = absl::StrCat(VcdName(signal.name), "_", n);
    vcd_names.push_back(name);
  }
  for (size_t i = 0; i < signals.size(); ++i) {
    absl::StrAppend(&out, "  ", vcd_names[i], ": ", signals[i].description, "\n");
  }
  absl::StrAppend(&out, "$end\n$timescale ", *timescale, " $end\n");

  // Scopes: stage/<scope parts>. Signals are listed grouped by scope, in signal order.
  absl::StrAppend(&out, "$scope module stage $end\n");
  std::vector<std::string> open;
  for (size_t i = 0; i < signals.size(); ++i) {
    std::vector<std::string> parts = absl::StrSplit(signals[i].scope, '/', absl::SkipEmpty());
    for (std::string& part : parts) part = VcdName(part);
    size_t common = 0;
    while (common < open.size() && common < parts.size() && open[common] == parts[common]) ++common;
    for (size_t k = open.size(); k > common; --k) absl::StrAppend(&out, "$upscope $end\n");
    open.resize(common);
    for (size_t k = common; k < parts.size(); ++k) {
      absl::StrAppend(&out, "$scope module ", parts[k], " $end\n");
      open.push_back(parts[k]);
    }
    // "pattern_id[3]" is written as reference "pattern_id [3]" (a bit select), which GTKWave coalesces into a bus.
    const std::string& name = vcd_names[i];
    const size_t bracket = name.find('[');
    const std::string ref =
        bracket == std::string::npos ? name : absl::StrCat(name.substr(0, bracket), " ", name.substr(bracket));
    absl::StrAppend(&out, "$var wire 1 ", code(i), " ", ref, " $end\n");
  }
  for (size_t k = open.size(); k > 0; --k) absl::StrAppend(&out, "$upscope $end\n");
  absl::StrAppend(&out, "$upscope $end\n$enddefinitions $end\n");

  // Edges in timescale units.
  struct Event {
    int64_t t;
    size_t signal;
    char value;
  };
  std::vector<Event> events;
  std::vector<char> initial(signals.size(), '0');
  for (size_t i = 0; i < signals.size(); ++i) {
    std::vector<Interval> units;
    for (size_t k = 0; k < signals[i].high.size(); ++k) {
      const Interval& iv = signals[i].high[k];
      units.push_back(
          {base.TicksToUnits(iv.first, options.timescale_fs), base.TicksToUnits(iv.second, options.timescale_fs)});
      // A pulse, or the gap before it, that rounds away would silently change the waveform: refuse instead.
      const bool pulse_lost = units.back().second <= units.back().first;
      const bool gap_lost = k > 0 && units.back().first <= units[k - 1].second;
      if (pulse_lost || gap_lost) {
        const int64_t ticks = pulse_lost ? iv.second - iv.first : iv.first - signals[i].high[k - 1].second;
        return absl::InvalidArgumentError(absl::StrFormat(
            "timescale %s is too coarse for this window: %s has a %s of %.3f us that it cannot show; use a timescale "
            "of at most half that",
            *timescale, VcdName(signals[i].name), pulse_lost ? "pulse" : "gap", base.TicksToUs(ticks)));
      }
    }
    for (const Interval& iv : Merge(std::move(units))) {
      if (iv.first <= u0) {
        initial[i] = '1';
      } else if (iv.first < u1) {
        events.push_back({iv.first, i, '1'});
      }
      if (iv.second < u1) events.push_back({iv.second, i, '0'});
    }
  }
  std::sort(events.begin(), events.end(),
            [](const Event& a, const Event& b) { return a.t != b.t ? a.t < b.t : a.signal < b.signal; });
  absl::StrAppend(&out, "#", u0, "\n$dumpvars\n");
  for (size_t i = 0; i < signals.size(); ++i) absl::StrAppend(&out, std::string(1, initial[i]), code(i), "\n");
  absl::StrAppend(&out, "$end\n");
  int64_t last = u0;
  for (const Event& e : events) {
    if (e.t != last) {
      absl::StrAppend(&out, "#", e.t, "\n");
      last = e.t;
    }
    absl::StrAppend(&out, std::string(1, e.value), code(e.signal), "\n");
  }
  // The end of the window, so that readers see how long the last values last.
  absl::StrAppend(&out, "#", u1, "\n");
  return out;
}

absl::StatusOr<std::string> ReportToSvg(const v1::TimingReport& report, const WaveformWindow& window) {
  if (window.slot_count <= 0) return absl::InvalidArgumentError("the waveform window has no slots");
  const v1::Schedule& schedule = report.schedule();
  const TimeBase base = TimeBase::FromProto(schedule.time_base());
  const int64_t T = base.ticks_per_slot();
  const int64_t w0 = base.SlotStartTicks(window.first_slot);
  const int64_t w1 = base.SlotStartTicks(window.first_slot + window.slot_count);
  const std::vector<Signal> signals = PlannedSignals(schedule, window);
  std::map<std::string, const Signal*> by_name;
  for (const Signal& s : signals) by_name[s.name] = &s;

  const double left = 190, plot_w = 1400, row_h = 18, top = window.slot_count <= 4 ? 70 : 120;
  const double px_per_slot = plot_w / static_cast<double>(window.slot_count);
  auto x = [&](int64_t t) { return left + static_cast<double>(t - w0) * plot_w / static_cast<double>(w1 - w0); };

  // Rows: slot clock, steady window, one per light node, one per camera.
  struct Row {
    std::string label;
    std::string device;
    bool camera = false;
  };
  std::vector<Row> rows = {{"slot clock", ""}, {"steady light", ""}};
  for (const auto& n : schedule.light_nodes()) rows.push_back({n.id() + " switching", n.id()});
  for (const auto& c : schedule.cameras()) rows.push_back({c.id(), c.id(), true});

  std::set<std::string> bad_devices;
  std::vector<const v1::Violation*> listed;
  for (const auto& v : report.violations()) {
    listed.push_back(&v);
    if (v.severity() == v1::SEVERITY_ERROR) bad_devices.insert(v.device());
  }
  const double plot_h = rows.size() * row_h;
  const double legend_top = top + plot_h + 40;
  const double height = legend_top + 24 + 16.0 * listed.size() + 20;
  const double width = left + plot_w + 30;

  std::string svg = absl::StrFormat(
      "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"%.0f\" height=\"%.0f\" viewBox=\"0 0 %.0f %.0f\" "
      "font-family=\"DejaVu Sans, Helvetica, Arial, sans-serif\" font-size=\"11\">\n",
      width, height, width, height);
  absl::StrAppend(&svg, "<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n");
  absl::StrAppend(
      &svg, absl::StrFormat("<text x=\"10\" y=\"18\" font-size=\"14\" font-weight=\"bold\">Schedule %s: "
                            "slots %d to %d of %s (%u slots/s, %.3f us each)</text>\n",
                            schedule.hash(), window.first_slot, window.first_slot + window.slot_count - 1,
                            XmlEscape(schedule.pattern_set()), schedule.time_base().slot_rate_hz(), base.TicksToUs(T)));
  absl::StrAppend(
      &svg,
      absl::StrFormat("<text x=\"10\" y=\"36\" fill=\"#444\">%d error(s), %d warning(s). Blue: "
                      "exposure; light blue: readout (thin: assumed); black tick: trigger; green: where an exposure "
                      "may be; grey: a light node switching; red: a violation.</text>\n",
                      report.errors(), report.warnings()));

  // Slot bands, slot numbers and pattern names.
  const int64_t n = CycleLength(schedule);
  const bool rotate = px_per_slot < 90;
  for (int64_t k = window.first_slot; k < window.first_slot + window.slot_count; ++k) {
    const double xa = x(base.SlotStartTicks(k)), xb = x(base.SlotStartTicks(k + 1));
    if ((k & 1) == 0) {
      absl::StrAppend(&svg, absl::StrFormat("<rect x=\"%.2f\" y=\"%.1f\" width=\"%.2f\" height=\"%.1f\" "
                                            "fill=\"#f3f3f3\"/>\n",
                                            xa, top, xb - xa, plot_h));
    }
    absl::StrAppend(&svg, absl::StrFormat("<line x1=\"%.2f\" y1=\"%.1f\" x2=\"%.2f\" y2=\"%.1f\" stroke=\"#bbb\" "
                                          "stroke-width=\"0.5\"/>\n",
                                          xa, top - 4, xa, top + plot_h));
    int64_t p = k % n;
    if (p < 0) p += n;
    const std::string name =
        XmlEscape(p < schedule.patterns_size() ? schedule.patterns(static_cast<int>(p)).name() : "");
    const double xc = (xa + xb) / 2;
    if (rotate) {
      absl::StrAppend(&svg, absl::StrFormat("<text x=\"%.2f\" y=\"%.1f\" transform=\"rotate(-90 %.2f %.1f)\" "
                                            "font-size=\"10\">%d %s</text>\n",
                                            xc + 3, top - 6, xc + 3, top - 6, k, name));
    } else {
      absl::StrAppend(&svg, absl::StrFormat("<text x=\"%.2f\" y=\"%.1f\" text-anchor=\"middle\">slot %d: %s</text>\n",
                                            xc, top - 8, k, name));
    }
  }
  // Time ticks in microseconds within a short window.
  if (window.slot_count <= 4) {
    const double total_us = base.TicksToUs(w1 - w0);
    const double step = total_us <= 1200 ? 100 : 500;
    for (double us = 0; us <= total_us + 1e-9; us += step) {
      const double xt = left + us / total_us * plot_w;
      absl::StrAppend(&svg, absl::StrFormat("<line x1=\"%.2f\" y1=\"%.1f\" x2=\"%.2f\" y2=\"%.1f\" stroke=\"#999\"/>"
                                            "<text x=\"%.2f\" y=\"%.1f\" text-anchor=\"middle\" fill=\"#555\">%.0f "
                                            "us</text>\n",
                                            xt, top + plot_h, xt, top + plot_h + 5, xt, top + plot_h + 17, us));
    }
  }

  auto boxes = [&](const std::string& signal, double y, double h, const char* fill, const char* extra = "") {
    auto it = by_name.find(signal);
    if (it == by_name.end()) return;
    for (const auto& [a, b] : it->second->high) {
      absl::StrAppend(&svg, absl::StrFormat("<rect x=\"%.2f\" y=\"%.1f\" width=\"%.2f\" height=\"%.1f\" fill=\"%s\" "
                                            "%s/>\n",
                                            x(a), y, std::max(0.5, x(b) - x(a)), h, fill, extra));
    }
  };
  for (size_t r = 0; r < rows.size(); ++r) {
    const Row& row = rows[r];
    const double y = top + r * row_h;
    const bool bad = bad_devices.count(row.device) > 0;
    absl::StrAppend(&svg, absl::StrFormat("<text x=\"%.1f\" y=\"%.1f\" text-anchor=\"end\" fill=\"%s\">%s</text>\n",
                                          left - 8, y + row_h - 5, bad ? "#c00000" : "#000", XmlEscape(row.label)));
    if (r == 0) {
      // Square wave.
      std::string points;
      const Signal& clock = *by_name["slot_clock"];
      double lo = y + row_h - 3, hi = y + 3;
      absl::StrAppend(&points, absl::StrFormat("%.2f,%.1f ", x(w0), lo));
      for (const auto& [a, b] : clock.high) {
        absl::StrAppend(&points, absl::StrFormat("%.2f,%.1f %.2f,%.1f %.2f,%.1f %.2f,%.1f ", x(a), lo, x(a), hi, x(b),
                                                 hi, x(b), lo));
      }
      absl::StrAppend(&points, absl::StrFormat("%.2f,%.1f", x(w1), lo));
      absl::StrAppend(&svg, absl::StrFormat("<polyline points=\"%s\" fill=\"none\" stroke=\"#333\" "
                                            "stroke-width=\"1\"/>\n",
                                            points));
    } else if (r == 1) {
      boxes("steady_window", y + 3, row_h - 6, "#9fd89f");
    } else if (!row.camera) {
      boxes(row.device + "_step", y + 3, row_h - 6, "#9a9a9a");
    } else {
      const v1::CameraTiming* c = FindCameraTiming(schedule, row.device);
      if (c != nullptr && c->readout_declared()) {
        boxes(row.device + "_readout", y + 4, row_h - 8, "#b9d3ee");
      } else {
        // Not declared: the verifier assumes the rest of the period; a thin line says "assumed".
        boxes(row.device + "_readout", y + row_h / 2 - 1, 2, "#b9d3ee");
      }
      boxes(row.device + "_exposure", y + 3, row_h - 6, "#3a6fb0");
      auto it = by_name.find(row.device + "_trigger");
      if (it != by_name.end()) {
        for (const auto& [a, b] : it->second->high) {
          absl::StrAppend(&svg, absl::StrFormat("<line x1=\"%.2f\" y1=\"%.1f\" x2=\"%.2f\" y2=\"%.1f\" "
                                                "stroke=\"black\" stroke-width=\"1.5\"/>\n",
                                                x(a), y + 1, x(a), y + row_h - 1));
        }
      }
    }
  }
  // Exposure outside the steady light, drawn where it happens in every slot of the window.
  for (const auto& v : report.violations()) {
    if (v.check() != kCheckSteadyLight) continue;
    const v1::CameraTiming* c = FindCameraTiming(schedule, v.device());
    if (c == nullptr) continue;
    size_t r = 0;
    while (r < rows.size() && rows[r].device != c->id()) ++r;
    const double y = top + r * row_h;
    const int64_t steady = schedule.steady_start_ticks();
    const int64_t last = schedule.steady_end_ticks() - schedule.guard_ticks();
    for (int64_t k = NextFiringSlot(*c, window.first_slot - c->divider()); k < window.first_slot + window.slot_count;
         k += c->divider()) {
      const int64_t s = base.SlotStartTicks(k);
      std::vector<Interval> bad;
      if (c->trigger_ticks() < steady)
        bad.push_back({s + c->trigger_ticks(), s + std::min(steady, c->trigger_ticks() + c->exposure_ticks())});
      if (c->trigger_ticks() + c->exposure_ticks() > last) {
        bad.push_back({s + std::max(last, c->trigger_ticks()), s + c->trigger_ticks() + c->exposure_ticks()});
      }
      for (auto [a, b] : bad) {
        a = std::max(a, w0);
        b = std::min(b, w1);
        if (b <= a) continue;
        absl::StrAppend(&svg, absl::StrFormat("<rect x=\"%.2f\" y=\"%.1f\" width=\"%.2f\" height=\"%.1f\" "
                                              "fill=\"#e00000\" stroke=\"#900\" stroke-width=\"0.5\"/>\n",
                                              x(a), y + 1, std::max(1.5, x(b) - x(a)), row_h - 2));
      }
    }
  }
  absl::StrAppend(&svg, absl::StrFormat("<rect x=\"%.1f\" y=\"%.1f\" width=\"%.1f\" height=\"%.1f\" fill=\"none\" "
                                        "stroke=\"#666\"/>\n",
                                        left, top, plot_w, plot_h));
  // Every violation under the diagram.
  absl::StrAppend(&svg, absl::StrFormat("<text x=\"10\" y=\"%.1f\" font-weight=\"bold\">%s</text>\n", legend_top,
                                        listed.empty() ? "No violations." : "Violations:"));
  double ly = legend_top + 18;
  for (const v1::Violation* v : listed) {
    const bool error = v->severity() == v1::SEVERITY_ERROR;
    std::string text = absl::StrCat(SeverityName(v->severity()), " [", v->check(), "] ", v->device(),
                                    v->slot() >= 0 ? absl::StrCat(" slot ", v->slot()) : "", ": ", v->message());
    if (text.size() > 260) text = text.substr(0, 257) + "...";
    absl::StrAppend(&svg, absl::StrFormat("<text x=\"10\" y=\"%.1f\" fill=\"%s\">%s</text>\n", ly,
                                          error ? "#c00000" : "#b06000", XmlEscape(text)));
    ly += 16;
  }
  absl::StrAppend(&svg, "</svg>\n");
  return svg;
}

}  // namespace stage::timing
