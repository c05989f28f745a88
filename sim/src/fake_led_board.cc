// A simulated LED driver board: libmodbus server for the register map of docs/led-board-modbus.md.
#include "stage/sim/fake_led_board.h"

#include <arpa/inet.h>
#include <modbus/modbus.h>
#include <netinet/in.h>
#include <sys/select.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>
#include <mutex>
#include <thread>

#include "absl/strings/str_cat.h"
#include "stage/common/logging.h"
#include "stage/light/led_board_map.h"
#include "stage/sim/scene.h"
#include "stage/sim/world_devices.h"
#include "stage/v1/rig.pb.h"

namespace stage::sim {

namespace b = light::board;

namespace {

int64_t SteadyNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

uint16_t Word(const uint8_t* p) { return static_cast<uint16_t>((p[0] << 8) | p[1]); }
void PutWord(uint8_t* p, uint16_t v) {
  p[0] = static_cast<uint8_t>(v >> 8);
  p[1] = static_cast<uint8_t>(v & 0xFF);
}

int16_t Tenths(double c) { return static_cast<int16_t>(std::lround(c * 10)); }

}  // namespace

absl::Status FakeLedBoardOptions::Validate() const {
  const std::string who = absl::StrCat("fake LED board \"", board_id, "\": ");
  if (channel_count < 1 || channel_count > 64) {
    return absl::InvalidArgumentError(absl::StrCat(who, "channel_count ", channel_count, " is not in 1..64"));
  }
  if (max_rows < 1 || max_rows > 64) {
    return absl::InvalidArgumentError(absl::StrCat(who, "max_rows ", max_rows, " is not in 1..64"));
  }
  if (unit_id < 1 || unit_id > 247) {
    return absl::InvalidArgumentError(absl::StrCat(who, "unit_id ", unit_id, " is not in 1..247"));
  }
  if (tcp_host.empty() == rtu_device.empty()) {
    return absl::InvalidArgumentError(absl::StrCat(who, "give exactly one of a TCP host and an RTU device"));
  }
  if (!tcp_host.empty() && (tcp_port < 0 || tcp_port > 65535)) {
    return absl::InvalidArgumentError(absl::StrCat(who, "TCP port ", tcp_port, " is not in 0..65535"));
  }
  if (!rtu_device.empty() && rtu_parity != 'N' && rtu_parity != 'E' && rtu_parity != 'O') {
    return absl::InvalidArgumentError(absl::StrCat(who, "parity '", std::string(1, rtu_parity), "' is not N, E or O"));
  }
  return absl::OkStatus();
}

class FakeLedBoard::Impl {
 public:
  explicit Impl(FakeLedBoardOptions options)
      : options_(std::move(options)), leds_(options_.board_id, options_.channel_count) {}

  ~Impl() {
    stop_.store(true);
    if (thread_.joinable()) thread_.join();
    for (int fd : clients_) close(fd);
    if (listen_fd_ >= 0) close(listen_fd_);
    if (ctx_ != nullptr) {
      if (options_.tcp_host.empty()) modbus_close(ctx_);
      modbus_free(ctx_);
    }
    if (store_ != nullptr) modbus_mapping_free(store_);
  }

  absl::Status Open() {
    const uint32_t size = b::kTable + options_.max_rows * options_.channel_count;
    store_ = modbus_mapping_new_start_address(0, 0, 0, 0, 0, size, 0, 0);
    if (store_ == nullptr) return absl::InternalError("fake LED board: out of memory");
    uint16_t* r = store_->tab_registers;
    r[b::kMagic] = b::kMagicValue;
    r[b::kMapVersion] = b::kMapVersionValue;
    r[b::kFirmwareVersion] = 0x0100;
    r[b::kChannelCount] = static_cast<uint16_t>(options_.channel_count);
    r[b::kMaxRows] = static_cast<uint16_t>(options_.max_rows);
    r[b::kSerialHi] = static_cast<uint16_t>(options_.serial >> 16);
    r[b::kSerialLo] = static_cast<uint16_t>(options_.serial & 0xFFFF);
    const char model[] = "FaStage sim LED";
    for (uint16_t i = 0; i < b::kModelRegisters; ++i) {
      const size_t at = 2u * i;
      const uint8_t hi = at < sizeof(model) - 1 ? static_cast<uint8_t>(model[at]) : 0;
      const uint8_t lo = at + 1 < sizeof(model) - 1 ? static_cast<uint8_t>(model[at + 1]) : 0;
      r[b::kModel + i] = static_cast<uint16_t>(hi << 8 | lo);
    }
    temperature_c_ = options_.temperature_c;
    RefreshStatus();

    const std::string who = absl::StrCat("fake LED board \"", options_.board_id, "\": ");
    if (!options_.tcp_host.empty()) {
      ctx_ = modbus_new_tcp(options_.tcp_host.c_str(), options_.tcp_port);
      if (ctx_ == nullptr) return absl::InternalError(absl::StrCat(who, "modbus_new_tcp: ", modbus_strerror(errno)));
      listen_fd_ = modbus_tcp_listen(ctx_, 8);
      if (listen_fd_ < 0) {
        return absl::UnavailableError(absl::StrCat(who, "cannot listen on ", options_.tcp_host, ":", options_.tcp_port,
                                                   ": ", modbus_strerror(errno)));
      }
      sockaddr_in addr{};
      socklen_t len = sizeof(addr);
      if (getsockname(listen_fd_, reinterpret_cast<sockaddr*>(&addr), &len) != 0) {
        return absl::InternalError(absl::StrCat(who, "getsockname: ", strerror(errno)));
      }
      port_ = ntohs(addr.sin_port);
    } else {
      ctx_ = modbus_new_rtu(options_.rtu_device.c_str(), options_.rtu_baud, options_.rtu_parity,
                            options_.rtu_data_bits, options_.rtu_stop_bits);
      if (ctx_ == nullptr) return absl::InvalidArgumentError(absl::StrCat(who, "modbus_new_rtu: ", modbus_strerror(errno)));
      modbus_set_slave(ctx_, options_.unit_id);
      if (modbus_connect(ctx_) != 0) {
        return absl::UnavailableError(
            absl::StrCat(who, "cannot open ", options_.rtu_device, ": ", modbus_strerror(errno)));
      }
    }
    thread_ = std::thread([this] { Serve(); });
    return absl::OkStatus();
  }

  std::string endpoint() const {
    return options_.tcp_host.empty() ? absl::StrCat("rtu:", options_.rtu_device)
                                     : absl::StrCat("tcp://", options_.tcp_host, ":", port_);
  }

  FakeLedBoardOptions options_;
  SimLightDriver leds_;
  int port_ = 0;

  // Fault knobs and the request log, guarded by mutex_ (as is the register store).
  mutable std::mutex mutex_;
  bool no_answer_ = false;
  int64_t answer_again_ns_ = 0;  // steady clock; 0: silent until told otherwise
  int corrupt_row_ = -1, corrupt_channel_ = -1;
  bool over_temperature_ = false;
  std::vector<BoardRequest> requests_;

  void SetOverTemperature(bool on) {
    std::lock_guard<std::mutex> lock(mutex_);
    over_temperature_ = on;
    temperature_c_ = on ? options_.temperature_limit_c + 4.5 : options_.temperature_c;
    if (on) EnterBlackout(b::kFaultOverTemperature, "over temperature");
    RefreshStatus();
  }

 private:
  uint16_t& reg(uint16_t address) { return store_->tab_registers[address]; }
  b::Mode mode() const { return static_cast<b::Mode>(store_->tab_registers[b::kMode]); }
  uint32_t table_end() const { return b::kTable + options_.max_rows * options_.channel_count; }

  // The board's CRC of its first sequence-length rows (0 when the length does not fit).
  uint16_t BoardCrc() {
    const uint32_t rows = reg(b::kSequenceLength);
    if (rows < 1 || rows > options_.max_rows) return 0;
    return b::TableCrc({&store_->tab_registers[b::kTable], rows * options_.channel_count});
  }
  bool TableValid() {
    const uint32_t rows = reg(b::kSequenceLength);
    return rows >= 1 && rows <= options_.max_rows && BoardCrc() == reg(b::kTableCrcExpected);
  }

  void EnterBlackout(uint16_t fault, const char* why) {
    leds_.Blackout().IgnoreError();  // the sim LEDs cannot fail to go dark
    reg(b::kMode) = static_cast<uint16_t>(b::Mode::kBlackout);
    reg(b::kFaults) |= fault;
    Logger("sim")->warn("fake LED board {}: blackout ({})", options_.board_id, why);
  }

  void RefreshStatus() {
    const light::DriverState s = leds_.State();
    uint16_t status = 0;
    if (TableValid()) status |= b::kStatusTableValid;
    if (mode() == b::Mode::kArmed) status |= b::kStatusArmed;
    if (mode() == b::Mode::kBlackout) status |= b::kStatusBlackout;
    const light::ChannelLevels out = leds_.Outputs();
    if (std::any_of(out.begin(), out.end(), [](uint16_t v) { return v > 0; })) status |= b::kStatusLit;
    reg(b::kStatus) = status;
    reg(b::kCurrentStep) = s.current_row < 0 ? b::kDark : static_cast<uint16_t>(s.current_row);
    reg(b::kStepCountHi) = static_cast<uint16_t>(s.steps >> 16);
    reg(b::kStepCountLo) = static_cast<uint16_t>(s.steps & 0xFFFF);
    reg(b::kTemperature) = static_cast<uint16_t>(Tenths(temperature_c_));
    reg(b::kTableCrc) = BoardCrc();
    reg(b::kTemperatureLimit) = static_cast<uint16_t>(Tenths(options_.temperature_limit_c));
  }

  // Where a write may land, and whether it needs idle.
  enum class Region { kNone, kControl, kLimits, kTable };
  Region WriteRegion(uint32_t address, uint32_t count) const {
    const uint32_t end = address + count;
    if (address >= b::kMode && end <= b::kMode + b::kControlRegisters) return Region::kControl;
    if (address >= b::kCurrentLimit && end <= b::kCurrentLimit + options_.channel_count) return Region::kLimits;
    if (address >= b::kTable && end <= table_end()) return Region::kTable;
    return Region::kNone;
  }

  // Applies a write of `count` values at `payload` (big-endian words) to the store, with the board's rules. Returns a
  // Modbus exception code, or 0. On success the payload is rewritten to what the board now holds (a corrupted cell,
  // the resulting mode), so that libmodbus's reply, which copies the payload into the store, changes nothing.
  int ApplyWrite(uint16_t address, uint16_t count, uint8_t* payload) {
    const Region region = WriteRegion(address, count);
    if (region == Region::kNone || count == 0) return MODBUS_EXCEPTION_ILLEGAL_DATA_ADDRESS;
    const bool idle = mode() == b::Mode::kIdle;
    int mode_index = -1;
    for (uint16_t i = 0; i < count; ++i) {
      const uint16_t a = static_cast<uint16_t>(address + i);
      const uint16_t v = Word(payload + 2 * i);
      if (a == b::kMode) {
        if (v > 2) return MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE;
        mode_index = i;
      } else if (a == b::kSequenceLength && (v < 1 || v > options_.max_rows)) {
        return MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE;
      } else if (a != b::kWatchdogMs && !idle) {
        return MODBUS_EXCEPTION_SLAVE_OR_SERVER_BUSY;
      }
    }
    for (uint16_t i = 0; i < count; ++i) {
      const uint16_t a = static_cast<uint16_t>(address + i);
      if (a == b::kMode) continue;
      uint16_t v = Word(payload + 2 * i);
      if (region == Region::kTable && corrupt_row_ >= 0 &&
          a == b::TableAddress(static_cast<uint32_t>(corrupt_row_), static_cast<uint32_t>(corrupt_channel_),
                               options_.channel_count)) {
        v ^= 0x0100;
        PutWord(payload + 2 * i, v);
      }
      reg(a) = v;
    }
    if (mode_index >= 0) {
      if (int e = SetMode(static_cast<b::Mode>(Word(payload + 2 * mode_index))); e != 0) return e;
      PutWord(payload + 2 * mode_index, reg(b::kMode));
    }
    return 0;
  }

  int SetMode(b::Mode want) {
    const b::Mode now = mode();
    switch (want) {
      case b::Mode::kArmed: {
        if (now == b::Mode::kArmed) return 0;
        if (now == b::Mode::kBlackout) return MODBUS_EXCEPTION_SLAVE_OR_SERVER_FAILURE;
        if (!TableValid()) {
          reg(b::kFaults) |= b::kFaultTableInvalid;
          return MODBUS_EXCEPTION_SLAVE_OR_SERVER_FAILURE;
        }
        light::PatternTable table;
        const uint32_t rows = reg(b::kSequenceLength);
        for (uint32_t r = 0; r < rows; ++r) {
          const uint16_t* row = &store_->tab_registers[b::TableAddress(r, 0, options_.channel_count)];
          table.rows.emplace_back(row, row + options_.channel_count);
          table.row_names.push_back(absl::StrCat("row ", r));
        }
        if (!leds_.LoadPatternTable(table).ok() || !leds_.Arm().ok()) return MODBUS_EXCEPTION_SLAVE_OR_SERVER_FAILURE;
        reg(b::kMode) = static_cast<uint16_t>(b::Mode::kArmed);
        reg(b::kFaults) = 0;
        return 0;
      }
      case b::Mode::kBlackout:
        EnterBlackout(0, "commanded");
        return 0;
      case b::Mode::kIdle:
        if (now == b::Mode::kBlackout) {
          if (over_temperature_) return MODBUS_EXCEPTION_SLAVE_OR_SERVER_FAILURE;
          leds_.ResetBlackout().IgnoreError();
          reg(b::kFaults) = 0;
        } else if (now == b::Mode::kArmed) {
          leds_.Disarm().IgnoreError();
        }
        reg(b::kMode) = static_cast<uint16_t>(b::Mode::kIdle);
        return 0;
    }
    return MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE;
  }

  // One request: log it, apply its write, answer it (or not, with the no-answer fault).
  void Handle(uint8_t* req, int length) {
    const int hl = modbus_get_header_length(ctx_);
    if (length < hl + 5) return;
    std::lock_guard<std::mutex> lock(mutex_);
    BoardRequest logged;
    logged.function = req[hl];
    logged.at_ns = SteadyNs();
    uint8_t* p = req + hl + 1;
    int exception = 0;
    switch (logged.function) {
      case MODBUS_FC_READ_HOLDING_REGISTERS:
        logged.address = Word(p);
        logged.count = Word(p + 2);
        if (logged.address + logged.count > table_end()) exception = MODBUS_EXCEPTION_ILLEGAL_DATA_ADDRESS;
        break;
      case MODBUS_FC_WRITE_SINGLE_REGISTER:
        logged.address = Word(p);
        logged.count = 1;
        break;
      case MODBUS_FC_WRITE_MULTIPLE_REGISTERS:
        logged.address = Word(p);
        logged.count = Word(p + 2);
        if (length < hl + 6 + 2 * logged.count) return;
        break;
      case MODBUS_FC_WRITE_AND_READ_REGISTERS:
        logged.read_address = Word(p);
        logged.read_count = Word(p + 2);
        logged.address = Word(p + 4);
        logged.count = Word(p + 6);
        if (length < hl + 10 + 2 * logged.count) return;
        if (logged.read_address + logged.read_count > table_end()) exception = MODBUS_EXCEPTION_ILLEGAL_DATA_ADDRESS;
        break;
      default:
        exception = MODBUS_EXCEPTION_ILLEGAL_FUNCTION;
    }
    last_request_ns_ = logged.at_ns;
    if (no_answer_ && answer_again_ns_ > 0 && logged.at_ns >= answer_again_ns_) {
      no_answer_ = false;
      answer_again_ns_ = 0;
      Logger("sim")->info("fake LED board {}: answers again", options_.board_id);
    }
    if (no_answer_) {
      requests_.push_back(logged);
      return;
    }
    if (exception == 0) {
      switch (logged.function) {
        case MODBUS_FC_WRITE_SINGLE_REGISTER:
          exception = ApplyWrite(logged.address, 1, p + 2);
          break;
        case MODBUS_FC_WRITE_MULTIPLE_REGISTERS:
          exception = ApplyWrite(logged.address, logged.count, p + 5);
          break;
        case MODBUS_FC_WRITE_AND_READ_REGISTERS:
          exception = ApplyWrite(logged.address, logged.count, p + 9);
          break;
        default:
          break;
      }
    }
    RefreshStatus();
    logged.answered = true;
    requests_.push_back(logged);
    if (exception != 0) {
      modbus_reply_exception(ctx_, req, static_cast<unsigned>(exception));
    } else {
      modbus_reply(ctx_, req, length, store_);
    }
  }

  void CheckWatchdog() {
    std::lock_guard<std::mutex> lock(mutex_);
    const uint16_t ms = reg(b::kWatchdogMs);
    if (mode() == b::Mode::kArmed && ms > 0 && SteadyNs() - last_request_ns_ > int64_t{ms} * 1'000'000) {
      EnterBlackout(b::kFaultWatchdog, "watchdog: the host went quiet while armed");
    }
    RefreshStatus();
  }

  void Serve() {
    std::vector<uint8_t> req(MODBUS_TCP_MAX_ADU_LENGTH > MODBUS_RTU_MAX_ADU_LENGTH ? MODBUS_TCP_MAX_ADU_LENGTH
                                                                                  : MODBUS_RTU_MAX_ADU_LENGTH);
    const bool tcp = !options_.tcp_host.empty();
    while (!stop_.load()) {
      fd_set read_set;
      FD_ZERO(&read_set);
      int max_fd = -1;
      auto add = [&](int fd) {
        FD_SET(fd, &read_set);
        max_fd = std::max(max_fd, fd);
      };
      if (tcp) {
        add(listen_fd_);
        for (int fd : clients_) add(fd);
      } else {
        add(modbus_get_socket(ctx_));
      }
      timeval timeout{0, 10'000};
      const int ready = select(max_fd + 1, &read_set, nullptr, nullptr, &timeout);
      if (ready < 0 && errno != EINTR) {
        Logger("sim")->error("fake LED board {}: select: {}", options_.board_id, strerror(errno));
        break;
      }
      if (ready > 0 && tcp) {
        if (FD_ISSET(listen_fd_, &read_set)) {
          const int fd = accept(listen_fd_, nullptr, nullptr);
          if (fd >= 0) clients_.push_back(fd);
        }
        for (size_t i = 0; i < clients_.size();) {
          if (!FD_ISSET(clients_[i], &read_set)) {
            ++i;
            continue;
          }
          modbus_set_socket(ctx_, clients_[i]);
          const int rc = modbus_receive(ctx_, req.data());
          if (rc > 0) {
            Handle(req.data(), rc);
            ++i;
          } else if (rc < 0) {  // the client closed the connection (or sent garbage)
            close(clients_[i]);
            clients_.erase(clients_.begin() + static_cast<std::ptrdiff_t>(i));
          } else {
            ++i;
          }
        }
      } else if (ready > 0) {
        const int rc = modbus_receive(ctx_, req.data());
        if (rc > 0) Handle(req.data(), rc);
        if (rc < 0) modbus_flush(ctx_);  // a garbled frame: start over at the next one
      }
      CheckWatchdog();
    }
  }

  modbus_t* ctx_ = nullptr;
  modbus_mapping_t* store_ = nullptr;
  int listen_fd_ = -1;
  std::vector<int> clients_;  // serving thread only
  std::thread thread_;
  std::atomic<bool> stop_{false};
  double temperature_c_ = 0;    // guarded by mutex_
  int64_t last_request_ns_ = 0;  // guarded by mutex_
};

absl::StatusOr<std::unique_ptr<FakeLedBoard>> FakeLedBoard::Start(FakeLedBoardOptions options) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  auto impl = std::make_unique<Impl>(std::move(options));
  if (absl::Status s = impl->Open(); !s.ok()) return s;
  Logger("sim")->info("fake LED board {}: {} channels at {}", impl->options_.board_id, impl->options_.channel_count,
                      impl->endpoint());
  return std::unique_ptr<FakeLedBoard>(new FakeLedBoard(std::move(impl)));
}

FakeLedBoard::FakeLedBoard(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
FakeLedBoard::~FakeLedBoard() {
  // Out of the world first: its edge callback (JoinStage) uses the board, which goes down next.
  impl_->leds_.DetachWorld();
}

std::string FakeLedBoard::endpoint() const { return impl_->endpoint(); }
int FakeLedBoard::port() const { return impl_->port_; }
const FakeLedBoardOptions& FakeLedBoard::options() const { return impl_->options_; }
SimLightDriver& FakeLedBoard::leds() { return impl_->leds_; }

void FakeLedBoard::SetNoAnswer(bool on) {
  std::lock_guard<std::mutex> lock(impl_->mutex_);
  impl_->no_answer_ = on;
  impl_->answer_again_ns_ = 0;
}

void FakeLedBoard::SetNoAnswerFor(std::chrono::milliseconds wall) {
  std::lock_guard<std::mutex> lock(impl_->mutex_);
  impl_->no_answer_ = true;
  impl_->answer_again_ns_ = SteadyNs() + std::chrono::duration_cast<std::chrono::nanoseconds>(wall).count();
}

absl::StatusOr<FakeLedBoardOptions> FakeLedBoardOptionsForNode(const v1::LightNodeConfig& n, uint32_t serial) {
  if (n.backend() != v1::LIGHT_BACKEND_MODBUS) {
    return absl::InvalidArgumentError(absl::StrCat("light node \"", n.id(), "\": a fake LED board needs backend modbus"));
  }
  FakeLedBoardOptions o;
  o.board_id = n.id();
  o.channel_count = n.channel_count();
  o.unit_id = static_cast<int>(n.modbus().has_unit_id() ? n.modbus().unit_id() : 1);
  o.serial = serial;
  o.tcp_host = "127.0.0.1";
  o.tcp_port = 0;
  if (absl::Status s = o.Validate(); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat("light node \"", n.id(), "\": ", s.message()));
  }
  return o;
}

absl::StatusOr<std::unique_ptr<FakeLedBoard>> FakeLedBoard::StartFor(v1::LightNodeConfig* node) {
  auto options = FakeLedBoardOptionsForNode(*node);
  if (!options.ok()) return options.status();
  auto board = Start(*std::move(options));
  if (!board.ok()) return board.status();
  node->mutable_modbus()->mutable_tcp()->set_host("127.0.0.1");
  node->mutable_modbus()->mutable_tcp()->set_port(static_cast<uint32_t>((*board)->port()));
  return board;
}

absl::Status FakeLedBoard::JoinStage(const SimScene& scene, const std::string& node_id, WorldClient* world,
                                     bool arm) {
  const v1::SimFault fault = scene.Fault(node_id);
  std::function<void(int64_t)> on_edge;
  if (fault.has_board_silent_at_s()) {
    const auto at_ns = static_cast<int64_t>(std::llround(fault.board_silent_at_s() * 1e9));
    const auto wall = std::chrono::milliseconds(std::llround(fault.board_silent_s() * 1e3));
    auto started = std::make_shared<std::atomic<bool>>(false);
    on_edge = [this, at_ns, wall, started, node_id](int64_t since_slot0_ns) {
      if (since_slot0_ns < at_ns || started->exchange(true)) return;
      Logger("sim")->warn("fake LED board {}: stops answering for {} ms (fault)", node_id, wall.count());
      SetNoAnswerFor(wall);
    };
  }
  return JoinLightNode(&leds(), scene, node_id, world, nullptr, arm, std::move(on_edge));
}

void FakeLedBoard::SetCorruptEntry(int row, int channel) {
  std::lock_guard<std::mutex> lock(impl_->mutex_);
  impl_->corrupt_row_ = row;
  impl_->corrupt_channel_ = channel;
}

void FakeLedBoard::SetOverTemperature(bool on) { impl_->SetOverTemperature(on); }

std::vector<BoardRequest> FakeLedBoard::Requests() const {
  std::lock_guard<std::mutex> lock(impl_->mutex_);
  return impl_->requests_;
}

void FakeLedBoard::ClearRequests() {
  std::lock_guard<std::mutex> lock(impl_->mutex_);
  impl_->requests_.clear();
}

}  // namespace stage::sim
