// GPIO lines through libgpiod's v1 C++ API (Debian 12: libgpiodcxx 1.6). It throws std::system_error; every call here
// turns that into a status naming the chip, the line and the cause.
#include <gpiod.hpp>

#include <algorithm>
#include <cerrno>
#include <system_error>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "gpio_lines.h"

namespace stage::light {
namespace {

absl::Status FromException(const std::exception& e, const std::string& what) {
  const auto* sys = dynamic_cast<const std::system_error*>(&e);
  const std::string message = absl::StrCat(what, ": ", e.what());
  if (sys == nullptr) return absl::InternalError(message);
  switch (sys->code().value()) {
    case ENOENT:
    case ENODEV:
      return absl::NotFoundError(message);
    case EACCES:
    case EPERM:
      return absl::PermissionDeniedError(message);
    case EBUSY:
      return absl::UnavailableError(message);
    case EINVAL:
    case ERANGE:
      return absl::InvalidArgumentError(message);
    default:
      return absl::UnavailableError(message);
  }
}

class GpiodLines final : public GpioLines {
 public:
  absl::Status Open(const GpiodLinesOptions& options) {
    options_ = options;
    try {
      chip_.open(options.chip, gpiod::chip::OPEN_LOOKUP);
    } catch (const std::exception& e) {
      return FromException(e, absl::StrCat("GPIO chip \"", options.chip, "\""));
    }
    name_ = absl::StrCat(chip_.name(), " [", chip_.label(), "]");
    const unsigned int lines = chip_.num_lines();
    auto check = [&](uint32_t offset, const char* role) -> absl::Status {
      if (offset >= lines) {
        return absl::InvalidArgumentError(
            absl::StrCat(name_, " has ", lines, " lines; ", role, " line ", offset, " does not exist"));
      }
      return absl::OkStatus();
    };
    // libgpiod v1 requests at most line_bulk::MAX_LINES (64) lines at once: the outputs go in chunks.
    for (size_t start = 0; start < options.outputs.size(); start += gpiod::line_bulk::MAX_LINES) {
      const size_t end = std::min(options.outputs.size(), start + gpiod::line_bulk::MAX_LINES);
      std::vector<unsigned int> offsets(options.outputs.begin() + static_cast<long>(start),
                                        options.outputs.begin() + static_cast<long>(end));
      for (unsigned int o : offsets) {
        if (auto s = check(o, "output"); !s.ok()) return s;
      }
      try {
        gpiod::line_bulk bulk = chip_.get_lines(offsets);
        bulk.request({options.consumer, gpiod::line_request::DIRECTION_OUTPUT, 0},
                     std::vector<int>(offsets.size(), 0));
        outputs_.push_back(bulk);
      } catch (const std::exception& e) {
        return FromException(e, absl::StrCat(name_, " output lines ", absl::StrJoin(offsets, ",")));
      }
    }
    if (options.slot_clock_line) {
      if (auto s = check(*options.slot_clock_line, "slot clock"); !s.ok()) return s;
      try {
        clock_ = chip_.get_line(*options.slot_clock_line);
        if (options.drives_slot_clock) {
          clock_.request({options.consumer + "-clock", gpiod::line_request::DIRECTION_OUTPUT, 0}, 0);
        } else {
          clock_.request({options.consumer + "-clock", gpiod::line_request::EVENT_RISING_EDGE, 0});
        }
      } catch (const std::exception& e) {
        return FromException(e, absl::StrCat(name_, " slot clock line ", *options.slot_clock_line));
      }
    }
    return absl::OkStatus();
  }

  ~GpiodLines() override {
    try {
      for (auto& bulk : outputs_) bulk.release();
      if (clock_) clock_.release();
    } catch (const std::exception&) {
      // The kernel releases the lines with the file descriptors anyway.
    }
  }

  std::string Describe() const override {
    std::string d = absl::StrCat(name_, ", ", options_.outputs.size(), " outputs");
    if (options_.slot_clock_line) {
      absl::StrAppend(&d, ", slot clock ", options_.drives_slot_clock ? "out" : "in", " on line ",
                      *options_.slot_clock_line);
    }
    return d;
  }

  absl::Status SetOutputs(const std::vector<uint8_t>& values) override {
    if (values.size() != options_.outputs.size()) {
      return absl::InvalidArgumentError(
          absl::StrCat(name_, ": ", values.size(), " values for ", options_.outputs.size(), " output lines"));
    }
    size_t start = 0;
    for (auto& bulk : outputs_) {
      std::vector<int> chunk(values.begin() + static_cast<long>(start),
                             values.begin() + static_cast<long>(start + bulk.size()));
      try {
        bulk.set_values(chunk);
      } catch (const std::exception& e) {
        return FromException(e, absl::StrCat(name_, " output lines from ", options_.outputs[start]));
      }
      start += bulk.size();
    }
    return absl::OkStatus();
  }

  absl::StatusOr<std::vector<int64_t>> WaitEdges(std::chrono::nanoseconds timeout) override {
    std::vector<int64_t> edges;
    if (!clock_ || options_.drives_slot_clock) {
      return absl::FailedPreconditionError(absl::StrCat(name_, ": no slot clock input line"));
    }
    try {
      if (!clock_.event_wait(timeout)) return edges;
      for (const gpiod::line_event& e : clock_.event_read_multiple()) {
        if (e.event_type == gpiod::line_event::RISING_EDGE) edges.push_back(e.timestamp.count());
      }
    } catch (const std::exception& e) {
      return FromException(e, absl::StrCat(name_, " slot clock line ", *options_.slot_clock_line));
    }
    return edges;
  }

  absl::Status SetClock(bool high) override {
    if (!clock_ || !options_.drives_slot_clock) {
      return absl::FailedPreconditionError(absl::StrCat(name_, ": no slot clock output line"));
    }
    try {
      clock_.set_value(high ? 1 : 0);
    } catch (const std::exception& e) {
      return FromException(e, absl::StrCat(name_, " slot clock line ", *options_.slot_clock_line));
    }
    return absl::OkStatus();
  }

 private:
  GpiodLinesOptions options_;
  gpiod::chip chip_;
  std::string name_;
  std::vector<gpiod::line_bulk> outputs_;
  gpiod::line clock_;
};

}  // namespace

absl::StatusOr<std::unique_ptr<GpioLines>> OpenGpiodLines(const GpiodLinesOptions& options) {
  auto lines = std::make_unique<GpiodLines>();
  if (absl::Status s = lines->Open(options); !s.ok()) return s;
  return std::unique_ptr<GpioLines>(std::move(lines));
}

}  // namespace stage::light
