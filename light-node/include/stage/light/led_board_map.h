// The Modbus register map of a FaStage LED driver board (docs/led-board-modbus.md): shared by the light node's
// Modbus driver and the simulator's fake boards. Holding registers only, PDU (0-based) addresses. No libmodbus here.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>

namespace stage::light::board {

// Identity, read-only.
inline constexpr uint16_t kMagic = 0x0000;           // reads kMagicValue: "FS"
inline constexpr uint16_t kMapVersion = 0x0001;      // this map: kMapVersionValue
inline constexpr uint16_t kFirmwareVersion = 0x0002;  // major << 8 | minor
inline constexpr uint16_t kChannelCount = 0x0003;
inline constexpr uint16_t kMaxRows = 0x0004;  // pattern table capacity, rows
inline constexpr uint16_t kSerialHi = 0x0005;
inline constexpr uint16_t kSerialLo = 0x0006;
inline constexpr uint16_t kModel = 0x0008;  // 16 ASCII characters, two per register (high byte first), NUL-padded
inline constexpr uint16_t kModelRegisters = 8;
inline constexpr uint16_t kIdentityRegisters = 0x0010;  // 0x0000..0x000F

inline constexpr uint16_t kMagicValue = 0x4653;
inline constexpr uint16_t kMapVersionValue = 1;

// Control, read-write.
inline constexpr uint16_t kMode = 0x0100;            // Mode below
inline constexpr uint16_t kSequenceLength = 0x0101;  // rows stepped through, 1..max rows; written only in idle
inline constexpr uint16_t kTableCrcExpected = 0x0102;  // the host's CRC of the table it wrote (TableCrc)
inline constexpr uint16_t kWatchdogMs = 0x0103;  // armed and no request for this long: blackout (0 = off)
inline constexpr uint16_t kControlRegisters = 4;  // 0x0100..0x0103

enum class Mode : uint16_t {
  kIdle = 0,      // dark; table, limits and sequence length writable
  kArmed = 1,     // steps one row on each slot-clock edge, from the first row on the first edge
  kBlackout = 2,  // dark, latched until mode 0 is written (refused while over temperature)
};

// Status, read-only. One read of kStatusRegisters from kStatus is the status poll.
inline constexpr uint16_t kStatus = 0x0110;        // StatusBit
inline constexpr uint16_t kFaults = 0x0111;        // FaultBit, latched until the board leaves blackout / is re-armed
inline constexpr uint16_t kCurrentStep = 0x0112;   // row lit now, kDark when dark
inline constexpr uint16_t kStepCountHi = 0x0113;   // slot-clock edges stepped on since armed (32 bits)
inline constexpr uint16_t kStepCountLo = 0x0114;
inline constexpr uint16_t kTemperature = 0x0115;   // int16, 0.1 degC
inline constexpr uint16_t kTableCrc = 0x0116;      // the board's CRC over its first sequence-length rows
inline constexpr uint16_t kTemperatureLimit = 0x0117;  // int16, 0.1 degC: above it the board blacks out
inline constexpr uint16_t kStatusRegisters = 8;    // 0x0110..0x0117

inline constexpr uint16_t kDark = 0xFFFF;

enum StatusBit : uint16_t {
  kStatusTableValid = 1 << 0,  // kTableCrc == kTableCrcExpected and the sequence length fits
  kStatusArmed = 1 << 1,
  kStatusBlackout = 1 << 2,
  kStatusLit = 1 << 3,  // some channel is on now
};

enum FaultBit : uint16_t {
  kFaultOverTemperature = 1 << 0,
  kFaultOverCurrent = 1 << 1,
  kFaultWatchdog = 1 << 2,      // armed and the host went quiet for kWatchdogMs: blacked out
  kFaultTableInvalid = 1 << 3,  // asked to arm with a table whose CRC does not match
};

// Per-channel current limit, mA, read-write in idle: kCurrentLimit + channel. Full scale (65535) drives this current.
inline constexpr uint16_t kCurrentLimit = 0x0200;

// Pattern table, read-write in idle: level of channel c in row r at kTable + r * channel_count + c (rows packed, so
// a whole table is one contiguous block).
inline constexpr uint16_t kTable = 0x1000;

inline constexpr uint16_t TableAddress(uint32_t row, uint32_t channel, uint32_t channel_count) {
  return static_cast<uint16_t>(kTable + row * channel_count + channel);
}

// CRC-16/MODBUS (polynomial 0xA001 reflected, initial 0xFFFF) over the registers in order, each as two bytes, high
// byte first: the value of kTableCrcExpected for rows 0..n-1 of a table.
inline uint16_t TableCrc(std::span<const uint16_t> registers) {
  uint16_t crc = 0xFFFF;
  auto feed = [&crc](uint8_t byte) {
    crc ^= byte;
    for (int i = 0; i < 8; ++i) crc = (crc & 1) ? static_cast<uint16_t>((crc >> 1) ^ 0xA001) : (crc >> 1);
  };
  for (uint16_t r : registers) {
    feed(static_cast<uint8_t>(r >> 8));
    feed(static_cast<uint8_t>(r & 0xFF));
  }
  return crc;
}

// Names of the set bits of kFaults, for status text.
inline const char* FaultName(uint16_t bit) {
  switch (bit) {
    case kFaultOverTemperature:
      return "over temperature";
    case kFaultOverCurrent:
      return "over current";
    case kFaultWatchdog:
      return "watchdog (host went quiet while armed)";
    case kFaultTableInvalid:
      return "table CRC mismatch (arm refused)";
    default:
      return "unknown fault";
  }
}

}  // namespace stage::light::board
