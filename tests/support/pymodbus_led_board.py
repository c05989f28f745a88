#!/usr/bin/python3
"""A FaStage LED driver board (docs/led-board-modbus.md) served over Modbus TCP by pymodbus.

For the interoperability test: the light node's libmodbus driver must work against a Modbus stack we did not write.
Built on Debian 12's python3-pymodbus (3.0.0); run it with /usr/bin/python3. It prints `ready <port>` once it listens
and exits on SIGTERM or SIGINT. It has no slot clock, so an armed board never steps (current step stays 0xFFFF, step
count 0, never lit) and never heats up; the watchdog is checked when the next request arrives.

Exceptions: 0x01 for any function code but 0x03, 0x06, 0x10, 0x17; 0x02 outside the map (a request must lie within
one block) or a write to a read-only register; 0x03 a mode above 2 or a sequence length out of range; 0x04 arming
with an invalid table; 0x06 a write to the table, limits, sequence length or expected CRC while not idle, or arming
from blackout. pymodbus 3.0 turns any exception raised in a datastore into 0x04, so the datastore instead refuses the
whole write (writing nothing), notes the code, and the server's response_manipulator swaps the reply for that
exception. For 0x17 the read after a refused write still runs, but its reply is replaced.
"""

import argparse
import asyncio
import logging
import signal
import sys
import time

from pymodbus.datastore import ModbusServerContext
from pymodbus.interfaces import IModbusSlaveContext
from pymodbus.pdu import ExceptionResponse
from pymodbus.server import StartAsyncTcpServer

MAGIC, MAP_VERSION, FIRMWARE, SERIAL, MODEL = 0x4653, 1, 0x0102, 0x00C0FFEE, "pymodbus board"
MODE, SEQ_LEN, CRC_EXPECTED, WATCHDOG = 0x0100, 0x0101, 0x0102, 0x0103
STATUS, STATUS_REGISTERS, LIMITS, TABLE = 0x0110, 8, 0x0200, 0x1000
IDLE, ARMED, BLACKOUT = 0, 1, 2
TABLE_VALID, ST_ARMED, ST_BLACKOUT = 1 << 0, 1 << 1, 1 << 2  # bit 3 (lit) is never set: this board never steps
FAULT_WATCHDOG, FAULT_TABLE_INVALID = 1 << 2, 1 << 3
TEMPERATURE, TEMPERATURE_LIMIT, DARK = 250, 700, 0xFFFF
FUNCTION_CODES = (3, 6, 16, 23)


def crc16_modbus(registers):
    """CRC-16/MODBUS over registers, each as two bytes, high byte first."""
    crc = 0xFFFF
    for reg in registers:
        for byte in (reg >> 8, reg & 0xFF):
            crc ^= byte
            for _ in range(8):
                crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


class LedBoard(IModbusSlaveContext):
    """The board's registers; the status block is computed on every read."""

    def __init__(self, channels, max_rows):
        self.channels, self.max_rows = channels, max_rows
        model = MODEL.encode("ascii").ljust(16, b"\0")
        self.identity = [MAGIC, MAP_VERSION, FIRMWARE, channels, max_rows, SERIAL >> 16, SERIAL & 0xFFFF, 0] + [
            model[i] << 8 | model[i + 1] for i in range(0, 16, 2)]
        self.control = [IDLE, 0, 0, 0]  # mode, sequence length (0: nothing loaded yet), expected CRC, watchdog ms
        self.limits = [0] * channels
        self.table = [0] * (max_rows * channels)
        self.faults, self.crc_cache, self.pending_exception, self.last_request = 0, None, None, time.monotonic()
        self.blocks = [(0x0000, len(self.identity)), (MODE, len(self.control)), (STATUS, STATUS_REGISTERS),
                       (LIMITS, channels), (TABLE, len(self.table))]

    def reset(self):
        self.__init__(self.channels, self.max_rows)

    def board_crc(self):
        if self.crc_cache is None:
            self.crc_cache = crc16_modbus(self.table[:self.control[1] * self.channels])
        return self.crc_cache

    def table_valid(self):
        return 1 <= self.control[1] <= self.max_rows and self.board_crc() == self.control[2]

    def status_block(self):
        mode = self.control[0]
        status = (TABLE_VALID if self.table_valid() else 0) | (ST_ARMED if mode == ARMED else 0) | (
            ST_BLACKOUT if mode == BLACKOUT else 0)
        return [status, self.faults, DARK, 0, 0, TEMPERATURE, self.board_crc(), TEMPERATURE_LIMIT]

    def block(self, address, count):
        """The (start, registers) of the block that holds address..address+count-1, or None."""
        for start, size in self.blocks:
            if start <= address and address + count <= start + size:
                return start, {0x0000: self.identity, MODE: self.control, STATUS: None, LIMITS: self.limits,
                               TABLE: self.table}[start]
        return None

    def validate(self, fx, address, count=1):
        now = time.monotonic()  # every request reaches here first: the watchdog is fed (or found expired) here
        if self.control[0] == ARMED and self.control[3] and (now - self.last_request) * 1000 > self.control[3]:
            self.control[0], self.faults = BLACKOUT, self.faults | FAULT_WATCHDOG
        self.last_request = now
        return fx in FUNCTION_CODES and self.block(address, count) is not None

    def getValues(self, fx, address, count=1):
        start, regs = self.block(address, count)
        regs = self.status_block() if regs is None else regs
        return regs[address - start:address - start + count]

    def setValues(self, fx, address, values):
        start, regs = self.block(address, len(values))
        code = self.check_write(start, address, values)
        if code:
            self.pending_exception = code
            return
        mode = None
        for i, value in enumerate(values):
            if regs is self.control and address + i == MODE:
                mode = value  # applied after the other control registers of this write
            else:
                regs[address - start + i] = value
        self.crc_cache = None
        if mode is not None:
            self.set_mode(mode)

    def check_write(self, start, address, values):
        """The exception code refusing this write, or None."""
        if start in (0x0000, STATUS):
            return 0x02
        touches = set(range(address, address + len(values)))
        if MODE in touches and values[MODE - address] > BLACKOUT:
            return 0x03
        if SEQ_LEN in touches and not 1 <= values[SEQ_LEN - address] <= self.max_rows:
            return 0x03
        if self.control[0] != IDLE and (start in (LIMITS, TABLE) or touches & {SEQ_LEN, CRC_EXPECTED}):
            return 0x06
        return None

    def set_mode(self, mode):
        current = self.control[0]
        if mode == ARMED and current == IDLE:
            if self.table_valid():
                self.control[0], self.faults = ARMED, 0
            else:
                self.faults |= FAULT_TABLE_INVALID
                self.pending_exception = 0x04
        elif mode == ARMED and current == BLACKOUT:
            self.pending_exception = 0x06  # latched: write 0 first
        elif mode == IDLE and current == BLACKOUT:
            self.control[0], self.faults = IDLE, 0  # never over temperature, so leaving blackout always works
        elif mode != ARMED:
            self.control[0] = mode

    def manipulate(self, response):
        """pymodbus' response_manipulator: replace the reply with the exception the board chose, if any."""
        function_code = response.function_code & 0x7F
        code = 0x01 if function_code not in FUNCTION_CODES else self.pending_exception
        self.pending_exception = None
        if code:
            exception = ExceptionResponse(function_code, code)
            exception.transaction_id, exception.unit_id = response.transaction_id, response.unit_id
            response = exception
        return response, False


async def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=0, help="0 (default): any free port")
    parser.add_argument("--channels", type=int, default=64, choices=range(1, 65), metavar="1..64")
    parser.add_argument("--unit", type=int, default=1, help="slave id answered (default 1)")
    parser.add_argument("--max-rows", type=int, default=64)
    parser.add_argument("--debug", action="store_true", help="pymodbus debug log on stderr")
    args = parser.parse_args()
    if not 0 <= args.unit <= 247:
        parser.error("--unit: 0..247")
    if not 1 <= args.max_rows or TABLE + args.max_rows * args.channels > 0x10000:
        parser.error("--max-rows: the table must fit below register 0x10000")
    # pymodbus 3.0 calls logging.basicConfig itself on import and logs expected events (every exception reply, every
    # client disconnect) as errors: quiet unless asked.
    logging.getLogger("pymodbus").setLevel(logging.DEBUG if args.debug else logging.CRITICAL)

    board = LedBoard(args.channels, args.max_rows)
    context = ModbusServerContext(slaves={args.unit: board}, single=False)
    server = await StartAsyncTcpServer(context=context, address=(args.host, args.port), defer_start=True,
                                       allow_reuse_address=True, response_manipulator=board.manipulate)
    serving = asyncio.create_task(server.serve_forever())
    await asyncio.wait([server.serving, serving], return_when=asyncio.FIRST_COMPLETED)
    if serving.done():  # it could not listen
        sys.exit(f"pymodbus_led_board: cannot listen on {args.host}:{args.port}: {serving.exception()}")
    stop = asyncio.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        asyncio.get_running_loop().add_signal_handler(sig, stop.set)
    print(f"ready {server.server.sockets[0].getsockname()[1]}", flush=True)
    await stop.wait()
    await server.server_close()
    serving.cancel()


if __name__ == "__main__":
    asyncio.run(main())
    sys.exit(0)
