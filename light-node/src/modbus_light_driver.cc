// LED driver boards over Modbus (libmodbus).
#include "modbus_light_driver.h"

#include <modbus/modbus.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <set>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/strip.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "stage/common/logging.h"
#include "stage/light/led_board_map.h"
#include "take_faults.h"

namespace stage::light {

namespace b = board;

absl::Status ModbusDriverOptions::Validate() const {
  const std::string who = absl::StrCat("light node \"", node_id, "\": ");
  if (channel_count < 1 || channel_count > 64) {
    return absl::InvalidArgumentError(absl::StrCat(who, "channel_count ", channel_count, " is not in 1..64"));
  }
  if (settings.transport_case() == v1::ModbusLightSettings::TRANSPORT_NOT_SET) {
    return absl::InvalidArgumentError(absl::StrCat(who, "modbus needs tcp or rtu settings"));
  }
  if (!current_limits_ma.empty() && current_limits_ma.size() != channel_count) {
    return absl::InvalidArgumentError(absl::StrCat(who, current_limits_ma.size(), " current limits for ",
                                                   channel_count, " channels"));
  }
  if (poll_interval_ms < 10) {
    return absl::InvalidArgumentError(absl::StrCat(who, "poll_interval_ms ", poll_interval_ms, " is below 10"));
  }
  if (board_watchdog_ms < 0 || board_watchdog_ms > 65535 ||
      (board_watchdog_ms > 0 && board_watchdog_ms < 2 * poll_interval_ms)) {
    return absl::InvalidArgumentError(absl::StrCat(who, "board_watchdog_ms ", board_watchdog_ms,
                                                   " must be 0 or at least two poll intervals, at most 65535"));
  }
  return absl::OkStatus();
}

absl::StatusOr<ModbusDriverOptions> ModbusDriverOptionsFromRig(const v1::LightNodeConfig& config) {
  if (!config.has_modbus()) {
    return absl::InvalidArgumentError(absl::StrCat("light node \"", config.id(), "\": no modbus settings"));
  }
  ModbusDriverOptions o;
  o.node_id = config.id();
  o.channel_count = config.channel_count();
  o.settings = config.modbus();
  o.current_limits_ma.assign(config.channel_count(), 0);
  for (const v1::LedUnit& u : config.units()) {
    const v1::LedLimits& limits = u.has_limits() ? u.limits() : config.unit_limits();
    const auto ma = static_cast<uint16_t>(std::clamp(limits.max_current_ma(), 0.0, 65535.0));
    for (uint32_t ch : {u.parallel_channel(), u.cross_channel()}) {
      if (ch < o.current_limits_ma.size()) o.current_limits_ma[ch] = ma;
    }
  }
  return o;
}

ModbusLightDriver::ModbusLightDriver(ModbusDriverOptions options) : options_(std::move(options)) {
  const v1::ModbusLightSettings& s = options_.settings;
  endpoint_ = s.has_tcp() ? absl::StrCat("tcp://", s.tcp().host(), ":", s.tcp().port())
                          : absl::StrCat("rtu:", s.rtu().device(), "@", s.rtu().baud());
  state_.channel_count = options_.channel_count;
}

std::string ModbusLightDriver::Who() const {
  return absl::StrCat("light node \"", options_.node_id, "\" (board ", endpoint_, " unit ",
                      options_.settings.unit_id(), ")");
}

absl::Status ModbusLightDriver::Connect() {
  const v1::ModbusLightSettings& s = options_.settings;
  if (s.has_tcp()) {
    ctx_ = modbus_new_tcp_pi(s.tcp().host().c_str(), std::to_string(s.tcp().port()).c_str());
  } else {
    const char parity = s.rtu().parity().empty() ? 'N' : s.rtu().parity()[0];
    ctx_ = modbus_new_rtu(s.rtu().device().c_str(), static_cast<int>(s.rtu().baud()), parity,
                          static_cast<int>(s.rtu().data_bits()), static_cast<int>(s.rtu().stop_bits()));
  }
  if (ctx_ == nullptr) {
    return absl::InvalidArgumentError(absl::StrCat(Who(), ": bad Modbus settings: ", modbus_strerror(errno)));
  }
  modbus_set_slave(ctx_, static_cast<int>(s.unit_id()));
  const uint32_t ms = s.timeout_ms();
  modbus_set_response_timeout(ctx_, ms / 1000, (ms % 1000) * 1000);
  return absl::OkStatus();
}

absl::StatusOr<std::unique_ptr<ModbusLightDriver>> ModbusLightDriver::Open(ModbusDriverOptions options) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  std::unique_ptr<ModbusLightDriver> d(new ModbusLightDriver(std::move(options)));
  if (absl::Status s = d->Connect(); !s.ok()) return s;
  uint16_t id[b::kIdentityRegisters] = {};
  if (absl::Status s = d->Transact(Purpose::kSetup, "reading the board's identity", b::kMagic,
                                   [&] { return modbus_read_registers(d->ctx_, b::kMagic, b::kIdentityRegisters, id); });
      !s.ok()) {
    return s;
  }
  if (id[b::kMagic] != b::kMagicValue) {
    return absl::FailedPreconditionError(absl::StrFormat(
        "%s: not a FaStage LED board (register 0x0000 reads 0x%04X, not 0x%04X; docs/led-board-modbus.md)", d->Who(),
        id[b::kMagic], b::kMagicValue));
  }
  if (id[b::kMapVersion] != b::kMapVersionValue) {
    return absl::FailedPreconditionError(absl::StrCat(d->Who(), ": register map version ", id[b::kMapVersion],
                                                      ", this light node speaks version ", b::kMapVersionValue));
  }
  if (id[b::kChannelCount] != d->options_.channel_count) {
    return absl::FailedPreconditionError(absl::StrCat(d->Who(), ": the board has ", id[b::kChannelCount],
                                                      " channels, the rig says channel_count ",
                                                      d->options_.channel_count));
  }
  d->max_rows_ = id[b::kMaxRows];
  d->firmware_ = id[b::kFirmwareVersion];
  for (uint16_t i = 0; i < b::kModelRegisters; ++i) {
    for (char c : {static_cast<char>(id[b::kModel + i] >> 8), static_cast<char>(id[b::kModel + i] & 0xFF)}) {
      if (c != 0) d->model_.push_back(c);
    }
  }
  if (absl::Status s = d->PollStatus(Purpose::kSetup); !s.ok()) return s;
  if (d->State().mode == DriverMode::kArmed) {
    // Armed by an earlier run of this node: no take of ours is running, so the lights go dark.
    Logger("light.modbus")->warn("{}: found armed; disarming", d->Who());
    if (absl::Status s = d->Disarm(); !s.ok()) return s;
  }
  Logger("light.modbus")->info("{}: {} firmware {}.{}, {} channels, {} rows", d->Who(), d->model_, d->firmware_ >> 8,
                               d->firmware_ & 0xFF, id[b::kChannelCount], d->max_rows_);
  d->poll_thread_ = std::thread([p = d.get()] { p->PollLoop(); });
  return d;
}

ModbusLightDriver::~ModbusLightDriver() {
  {
    std::lock_guard<std::mutex> lock(poll_mutex_);
    stopping_ = true;
  }
  poll_wake_.notify_all();
  if (poll_thread_.joinable()) poll_thread_.join();
  if (ctx_ != nullptr) {
    modbus_close(ctx_);
    modbus_free(ctx_);
  }
}

DriverDescription ModbusLightDriver::Describe() const {
  return {"modbus", absl::StrCat(endpoint_, " unit ", options_.settings.unit_id()), options_.channel_count};
}

absl::Status ModbusLightDriver::Transact(Purpose purpose, const std::string& what, uint16_t address,
                                         const std::function<int()>& call) {
  if (take_window_.load() && purpose != Purpose::kStatusPoll && purpose != Purpose::kDisarm &&
      purpose != Purpose::kBlackout) {
    refused_.fetch_add(1);
    return absl::FailedPreconditionError(
        absl::StrCat(Who(), ": ", what, " refused: the board is armed, and until the take ends only the status poll, "
                                        "disarm and blackout go on the bus"));
  }
  std::lock_guard<std::mutex> lock(bus_mutex_);
  const int tries = 1 + static_cast<int>(options_.settings.retries());
  int err = 0;
  for (int t = 0; t < tries; ++t) {
    if (modbus_get_socket(ctx_) < 0 && modbus_connect(ctx_) != 0) {
      err = errno;
      modbus_close(ctx_);
      continue;
    }
    transactions_.fetch_add(1);
    if (call() >= 0) return absl::OkStatus();
    err = errno;
    if (err >= EMBXILFUN && err <= EMBXGTAR) {
      // The board answered with an exception: it heard us and said no; asking again would not change that.
      return absl::FailedPreconditionError(absl::StrFormat("%s: %s (register 0x%04X): the board answered \"%s\"",
                                                           Who(), what, address, modbus_strerror(err)));
    }
    // Timed out, or the link broke: start from a fresh connection so that a late answer cannot be taken for the
    // next one's.
    modbus_flush(ctx_);
    modbus_close(ctx_);
  }
  return absl::UnavailableError(absl::StrFormat("%s: %s (register 0x%04X): %s, %d %s; the board is not answering",
                                                Who(), what, address, modbus_strerror(err), tries,
                                                tries == 1 ? "try" : "tries"));
}

void ModbusLightDriver::ApplyStatus(const uint16_t* r) {
  const uint16_t status = r[b::kStatus - b::kStatus];
  const uint16_t faults = r[b::kFaults - b::kStatus];
  const DriverMode mode = (status & b::kStatusBlackout) ? DriverMode::kBlackout
                          : (status & b::kStatusArmed)  ? DriverMode::kArmed
                                                        : DriverMode::kIdle;
  if (mode == DriverMode::kBlackout && take_window_.load()) {
    // The board blacked out by itself (temperature, watchdog): nothing steps any more.
    take_window_.store(false);
  }
  state_.mode = mode;
  const uint16_t step = r[b::kCurrentStep - b::kStatus];
  state_.current_row = step == b::kDark ? -1 : step;
  state_.steps = (uint64_t{r[b::kStepCountHi - b::kStatus]} << 16) | r[b::kStepCountLo - b::kStatus];
  state_.temperature_c = static_cast<int16_t>(r[b::kTemperature - b::kStatus]) / 10.0;
  board_faults_.clear();
  for (uint16_t bit = 1; bit != 0; bit = static_cast<uint16_t>(bit << 1)) {
    if (!(faults & bit)) continue;
    board_faults_.emplace_back(absl::StrCat("board: ", b::FaultName(bit)),
                               bit == b::kFaultOverTemperature
                                   ? absl::StrFormat(" (%.1f degC, limit %.1f degC)", *state_.temperature_c,
                                                     static_cast<int16_t>(r[b::kTemperatureLimit - b::kStatus]) / 10.0)
                                   : std::string());
  }
  state_.faults.clear();
  for (const auto& [kind, detail] : board_faults_) state_.faults.push_back(kind + detail);
}

void ModbusLightDriver::NoteBoardFault(const std::string& kind, const std::string& detail) {
  // With state_mutex_ held. Once per kind per take, stamped with when it was first seen.
  RecordTakeFault(&state_.take_faults, kind, detail);
}

absl::Status ModbusLightDriver::PollStatus(Purpose purpose) {
  uint16_t r[b::kStatusRegisters] = {};
  absl::Status s = Transact(purpose, "status poll", b::kStatus,
                            [&] { return modbus_read_registers(ctx_, b::kStatus, b::kStatusRegisters, r); });
  std::lock_guard<std::mutex> lock(state_mutex_);
  if (s.ok()) {
    ApplyStatus(r);
    link_fault_.clear();
  } else if (!absl::IsFailedPrecondition(s)) {
    link_fault_ = std::string(s.message());
  }
  if (take_window_.load() || state_.mode == DriverMode::kBlackout) {
    for (const auto& [kind, detail] : board_faults_) NoteBoardFault(kind, detail);
  }
  if (!link_fault_.empty() && (take_window_.load() || state_.mode == DriverMode::kArmed)) {
    // "board not answering: status poll (register 0x0110): Connection timed out, 3 tries" (the node is named by
    // whoever reads it); one outage is one take fault, with the cause first seen.
    absl::string_view cause = link_fault_;
    absl::ConsumePrefix(&cause, Who() + ": ");
    absl::ConsumeSuffix(&cause, "; the board is not answering");
    NoteBoardFault("board not answering", absl::StrCat(": ", cause));
  }
  return s;
}

absl::Status ModbusLightDriver::ReadStatusNow() { return PollStatus(Purpose::kSetup); }

void ModbusLightDriver::PollLoop() {
  std::unique_lock<std::mutex> lock(poll_mutex_);
  while (!stopping_) {
    if (poll_wake_.wait_for(lock, std::chrono::milliseconds(options_.poll_interval_ms), [this] { return stopping_; })) {
      break;
    }
    lock.unlock();
    if (absl::Status s = PollStatus(Purpose::kStatusPoll); !s.ok() && !absl::IsFailedPrecondition(s)) {
      Logger("light.modbus")->warn("{}", s.message());
    }
    lock.lock();
  }
}

DriverState ModbusLightDriver::State() const {
  std::lock_guard<std::mutex> lock(state_mutex_);
  DriverState s = state_;
  if (!link_fault_.empty()) s.faults.push_back(link_fault_);
  return s;
}

absl::Status ModbusLightDriver::LoadPatternTable(const PatternTable& table) {
  const uint32_t n = options_.channel_count;
  if (table.rows.empty()) return absl::InvalidArgumentError(absl::StrCat(Who(), ": the pattern table has no rows"));
  if (table.rows.size() > max_rows_) {
    return absl::InvalidArgumentError(absl::StrCat(Who(), ": the pattern table has ", table.rows.size(),
                                                   " rows, the board holds at most ", max_rows_));
  }
  std::vector<uint16_t> flat;
  flat.reserve(table.rows.size() * n);
  for (size_t r = 0; r < table.rows.size(); ++r) {
    if (table.rows[r].size() != n) {
      return absl::InvalidArgumentError(absl::StrCat(Who(), ": pattern table row ", r, " has ", table.rows[r].size(),
                                                     " levels, the node has ", n, " channels"));
    }
    flat.insert(flat.end(), table.rows[r].begin(), table.rows[r].end());
  }
  if (State().mode != DriverMode::kIdle) {
    return absl::FailedPreconditionError(absl::StrCat(Who(), ": load a table only when idle"));
  }
  auto row_name = [&](size_t r) {
    return r < table.row_names.size() && !table.row_names[r].empty() ? absl::StrCat(" (", table.row_names[r], ")")
                                                                      : std::string();
  };
  // The table: each block written and read back in one transaction.
  std::vector<uint16_t> back(MODBUS_MAX_WR_WRITE_REGISTERS);
  for (size_t off = 0; off < flat.size(); off += MODBUS_MAX_WR_WRITE_REGISTERS) {
    const int count = static_cast<int>(std::min<size_t>(MODBUS_MAX_WR_WRITE_REGISTERS, flat.size() - off));
    const auto address = static_cast<uint16_t>(b::kTable + off);
    if (absl::Status s = Transact(Purpose::kSetup, "writing the pattern table", address,
                                  [&] {
                                    return modbus_write_and_read_registers(ctx_, address, count, &flat[off], address,
                                                                           count, back.data());
                                  });
        !s.ok()) {
      return s;
    }
    for (int i = 0; i < count; ++i) {
      if (back[static_cast<size_t>(i)] != flat[off + static_cast<size_t>(i)]) {
        const size_t entry = off + static_cast<size_t>(i);
        return absl::DataLossError(absl::StrFormat(
            "%s: the pattern table reads back wrong at row %d%s channel %d (register 0x%04X): wrote %d, the board "
            "holds %d; not armed",
            Who(), entry / n, row_name(entry / n), entry % n, address + i, flat[entry], back[static_cast<size_t>(i)]));
      }
    }
  }
  // Current limits.
  if (!options_.current_limits_ma.empty()) {
    std::vector<uint16_t> limits = options_.current_limits_ma;
    std::vector<uint16_t> read(n);
    if (absl::Status s = Transact(Purpose::kSetup, "writing the current limits", b::kCurrentLimit,
                                  [&] {
                                    return modbus_write_and_read_registers(ctx_, b::kCurrentLimit, static_cast<int>(n),
                                                                           limits.data(), b::kCurrentLimit,
                                                                           static_cast<int>(n), read.data());
                                  });
        !s.ok()) {
      return s;
    }
    for (uint32_t c = 0; c < n; ++c) {
      if (read[c] != limits[c]) {
        return absl::DataLossError(absl::StrFormat(
            "%s: the current limit of channel %d (register 0x%04X) reads back %d mA, wrote %d mA; not armed", Who(), c,
            b::kCurrentLimit + c, read[c], limits[c]));
      }
    }
  }
  // Sequence length, the expected CRC and the watchdog; the status block tells whether the board agrees.
  const uint16_t crc = b::TableCrc(flat);
  uint16_t control[3] = {static_cast<uint16_t>(table.rows.size()), crc,
                         static_cast<uint16_t>(options_.board_watchdog_ms)};
  uint16_t status[b::kStatusRegisters] = {};
  if (absl::Status s = Transact(Purpose::kSetup, "committing the pattern table", b::kSequenceLength,
                                [&] {
                                  return modbus_write_and_read_registers(ctx_, b::kSequenceLength, 3, control,
                                                                         b::kStatus, b::kStatusRegisters, status);
                                });
      !s.ok()) {
    return s;
  }
  {
    std::lock_guard<std::mutex> lock(state_mutex_);
    ApplyStatus(status);
  }
  const uint16_t board_crc = status[b::kTableCrc - b::kStatus];
  if (board_crc != crc || !(status[0] & b::kStatusTableValid)) {
    return absl::DataLossError(absl::StrFormat(
        "%s: the board's CRC of its %d-row table is 0x%04X, the table's is 0x%04X (register 0x%04X); not armed", Who(),
        table.rows.size(), board_crc, crc, b::kTableCrc));
  }
  return absl::OkStatus();
}

absl::Status ModbusLightDriver::Arm() {
  if (State().mode != DriverMode::kIdle) {
    return absl::FailedPreconditionError(absl::StrCat(Who(), ": arm only when idle"));
  }
  uint16_t armed = static_cast<uint16_t>(b::Mode::kArmed);
  uint16_t status[b::kStatusRegisters] = {};
  if (absl::Status s = Transact(Purpose::kArm, "arming", b::kMode,
                                [&] {
                                  return modbus_write_and_read_registers(ctx_, b::kMode, 1, &armed, b::kStatus,
                                                                         b::kStatusRegisters, status);
                                });
      !s.ok()) {
    return s;
  }
  std::lock_guard<std::mutex> lock(state_mutex_);
  ApplyStatus(status);
  if (state_.mode != DriverMode::kArmed) {
    return absl::InternalError(absl::StrFormat("%s: the board took the arm command but reports status 0x%04X", Who(),
                                               status[0]));
  }
  state_.take_faults.clear();
  take_window_.store(true);
  return absl::OkStatus();
}

absl::Status ModbusLightDriver::Disarm() {
  absl::Status s = Transact(Purpose::kDisarm, "disarming", b::kMode,
                            [&] { return modbus_write_register(ctx_, b::kMode, static_cast<int>(b::Mode::kIdle)); });
  take_window_.store(false);
  if (!s.ok()) return s;
  return PollStatus(Purpose::kSetup);
}

absl::Status ModbusLightDriver::Blackout() {
  absl::Status s = Transact(Purpose::kBlackout, "blackout", b::kMode,
                            [&] { return modbus_write_register(ctx_, b::kMode, static_cast<int>(b::Mode::kBlackout)); });
  take_window_.store(false);
  std::lock_guard<std::mutex> lock(state_mutex_);
  if (s.ok()) {
    state_.mode = DriverMode::kBlackout;
    state_.current_row = -1;
  } else {
    NoteBoardFault("blackout not confirmed by the board (its lights may be on)");
  }
  return s;
}

absl::Status ModbusLightDriver::ResetBlackout() {
  if (absl::Status s = Transact(Purpose::kSetup, "leaving blackout", b::kMode,
                                [&] { return modbus_write_register(ctx_, b::kMode, static_cast<int>(b::Mode::kIdle)); });
      !s.ok()) {
    return s;
  }
  return PollStatus(Purpose::kSetup);
}

}  // namespace stage::light
