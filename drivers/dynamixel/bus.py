"""The wire: ``dynamixel_sdk`` Protocol 2.0 calls with bounded retries and typed errors.

Every transaction goes through :meth:`DxlBus._transact`: COMM_RX_TIMEOUT / COMM_RX_CORRUPT (and a busy
port left behind by a failed call) are retried ``retries`` times, then raised as ``ConnectionLost``
(nothing answered) or ``BusError`` (answers were damaged).

Status Return Level (68): a device below 2 answers no write and no reboot (e-Manual, Status Return Level;
Protocol 2.0): :attr:`DxlBus.status_level` per id makes :meth:`write` and :meth:`reboot` send without waiting
for a status that will not come (the caller reads back what it wrote)."""

from __future__ import annotations

import contextlib
import select
import threading
import time
from collections.abc import Callable

from station.robot.errors import BusError, ConfigError, ConnectionLost
from station.robot.registry import bus_library

with bus_library("pyserial"):
    import serial  # noqa: F401 - dynamixel_sdk's transport: named here so a missing one is named right
with bus_library("dynamixel-sdk"):
    import dynamixel_sdk as sdk

RETRYABLE = (sdk.COMM_RX_TIMEOUT, sdk.COMM_RX_CORRUPT, sdk.COMM_RX_FAIL, sdk.COMM_PORT_BUSY)


class DxlPort(sdk.PortHandler):
    """The SDK's PortHandler with its answer timeout's latency term configurable: the SDK waits
    ``bytes x byte time + 2 x 16 ms (FTDI latency timer) + 2 ms``. With the adapter's latency timer set to
    1 ms, ``latency_ms=1`` detects a lost answer 30 ms sooner; on a loaded host (or CI) a larger value keeps
    scheduling delays from counting as lost answers."""

    def __init__(self, port_name: str, latency_ms: float = sdk.port_handler.LATENCY_TIMER) -> None:
        super().__init__(port_name)
        self.latency_ms = float(latency_ms)

    def readPort(self, length):  # noqa: N802 - SDK method name
        """The SDK calls this in a tight loop until the answer is complete or its packet timeout passes (the
        port is non-blocking): with nothing to read yet, wait in ``select`` for the next byte (at most 5 ms,
        so the SDK's timeout checks stay on time) instead of spinning, which held a core and the GIL."""
        data = self.ser.read(length)
        if data or length <= 0:
            return data
        left_ms = self.packet_timeout - self.getTimeSinceStart()
        if left_ms > 0:
            with contextlib.suppress(OSError, ValueError):
                select.select([self.ser.fileno()], [], [], min(left_ms / 1000.0, 0.005))
        return self.ser.read(length)

    def setPacketTimeout(self, packet_length):  # noqa: N802 - SDK method name
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = (self.tx_time_per_byte * packet_length) + (self.latency_ms * 2.0) + 2.0


def _signed(value: int, size: int) -> int:
    bits = 8 * size
    return value - (1 << bits) if value >= 1 << (bits - 1) else value


class DxlBus:
    def __init__(self, path: str, baud: int, retries: int = 3,
                 latency_ms: float = sdk.port_handler.LATENCY_TIMER) -> None:
        self.path = path
        self.retries = max(0, int(retries))
        self.port = DxlPort(path, latency_ms)
        self.ph = sdk.PacketHandler(2.0)
        self.transactions = 0  # instruction packets sent (retries included)
        self.retried = 0
        self.status_level: dict[int, int] = {}  # Status Return Level (68) per id, as read at connect (default 2)
        self._lock = threading.RLock()  # one transaction at a time (a UI may poll status while jogging)
        # the station's own silences on the bus: a servo's Bus Watchdog (98) trips when it hears nothing for its
        # period, and the driver must know whether that silence was its own (a loaded host) or lost packets
        self._last_io = time.monotonic()
        self._quiet = 0.0
        try:
            ok = self.port.openPort() and self.port.setBaudRate(int(baud))
        except Exception as e:  # pyserial raises SerialException/OSError for a missing or busy port
            raise BusError(f"dynamixel: cannot open {path}: {e}") from None
        if not ok:
            raise ConfigError(f"dynamixel: {path}: baud rate {baud} not supported by the SDK")
        self.baud = int(baud)

    def close(self) -> None:
        if self.port.is_open:
            self.port.closePort()

    # ---- core -----------------------------------------------------------------------------
    def _transact(self, what: str, fn: Callable[[], tuple], retry: bool = True):
        """``fn() -> (result_code, *values)``; returns ``values`` on success."""
        with self._lock:
            self._quiet = max(self._quiet, time.monotonic() - self._last_io)
            try:
                return self._transact_locked(what, fn, retry)
            finally:
                self._last_io = time.monotonic()

    def quiet_from_now(self) -> None:
        """Start measuring the longest silence: from now, the longest time between one transaction's end and
        the next one's start (``longest_quiet``, s)."""
        with self._lock:
            self._last_io = time.monotonic()
            self._quiet = 0.0

    @property
    def longest_quiet(self) -> float:
        """Seconds: the longest time the station sent nothing since ``quiet_from_now`` (up to now)."""
        with self._lock:
            return max(self._quiet, time.monotonic() - self._last_io)

    def _transact_locked(self, what: str, fn: Callable[[], tuple], retry: bool):
        results = []
        for attempt in range(1 + (self.retries if retry else 0)):
            if attempt:
                self.retried += 1
            self.port.is_using = False  # a failed SDK call can leave the port marked busy
            self.transactions += 1
            try:
                out = fn()
            except Exception as e:  # pyserial: SerialException/OSError when the adapter or its pty is gone
                self.port.is_using = False
                raise ConnectionLost(f"dynamixel bus {self.path}: {what}: the serial port failed ({e}); check the "
                                     "USB adapter and its cable") from None
            res = out[0]
            if res == sdk.COMM_SUCCESS:
                return out[1:]
            results.append(res)
            if res not in RETRYABLE:
                break
        self.port.is_using = False
        text = self.ph.getTxRxResult(results[-1])
        n = len(results)
        if all(r == sdk.COMM_RX_TIMEOUT for r in results):
            raise ConnectionLost(f"dynamixel bus {self.path}: {what}: no answer ({text}) after {n} attempt(s)")
        raise BusError(f"dynamixel bus {self.path}: {what}: {text} after {n} attempt(s)")

    # ---- unicast ------------------------------------------------------------------------------
    def ping(self, dxl_id: int, retry: bool = True) -> tuple[int, int]:
        """``(model_number, error)``."""
        def call():
            model, res, err = self.ph.ping(self.port, dxl_id)
            return res, model, err
        return self._transact(f"ping id {dxl_id}", call, retry)

    def read_block(self, dxl_id: int, addr: int, size: int, retry: bool = True) -> tuple[bytes, int]:
        """``(data, error)`` of ``size`` bytes from ``addr`` (one Read instruction). An answer of another length
        is a corrupt one (retried): a status that came too late for an earlier instruction of this id carries the
        same id and would otherwise pass for this one (Protocol 2.0 has no sequence number)."""
        def call():
            data, res, err = self.ph.readTxRx(self.port, dxl_id, addr, size)
            if res == sdk.COMM_SUCCESS and len(data or ()) != size:
                return sdk.COMM_RX_CORRUPT, b"", err
            return res, bytes(data or b""), err
        return self._transact(f"read id {dxl_id} address {addr}" + (f"+{size}" if size > 4 else ""), call, retry)

    def read(self, dxl_id: int, addr: int, size: int, signed: bool = False, retry: bool = True) -> tuple[int, int]:
        """``(value, error)`` of a 1/2/4-byte item."""
        data, err = self.read_block(dxl_id, addr, size, retry)
        return int.from_bytes(data, "little", signed=signed), err

    def answers_writes(self, dxl_id: int) -> bool:
        return self.status_level.get(dxl_id, 2) >= 2

    def write(self, dxl_id: int, addr: int, size: int, value: int, retry: bool = True) -> int:
        """Write; returns the status error byte, or 0 from a device whose Status Return Level sends none for a
        write (then only a read-back tells whether it took the value)."""
        v = int(value) & ((1 << (8 * size)) - 1)
        if not self.answers_writes(dxl_id):
            tx = {1: self.ph.write1ByteTxOnly, 2: self.ph.write2ByteTxOnly, 4: self.ph.write4ByteTxOnly}[size]
            self._transact(f"write id {dxl_id} address {addr}", lambda: (tx(self.port, dxl_id, addr, v),))
            return 0
        fn = {1: self.ph.write1ByteTxRx, 2: self.ph.write2ByteTxRx, 4: self.ph.write4ByteTxRx}[size]

        def call():
            res, err = fn(self.port, dxl_id, addr, v)
            return res, err
        (err,) = self._transact(f"write id {dxl_id} address {addr}", call, retry)
        return err

    def reboot(self, dxl_id: int) -> int:
        """Reboot instruction; its status only from a device at Status Return Level 2 (else 0, nothing awaited)."""
        if not self.answers_writes(dxl_id):
            packet = [0] * 10  # the SDK's own packet layout: header, id, length 3, instruction, CRC (txPacket)
            packet[sdk.protocol2_packet_handler.PKT_ID] = dxl_id
            packet[sdk.protocol2_packet_handler.PKT_LENGTH_L] = 3
            packet[sdk.protocol2_packet_handler.PKT_INSTRUCTION] = sdk.INST_REBOOT

            def send():
                res = self.ph.txPacket(self.port, packet)
                self.port.is_using = False
                return (res,)
            self._transact(f"reboot id {dxl_id}", send)
            return 0

        def call():
            res, err = self.ph.reboot(self.port, dxl_id)
            return res, err
        (err,) = self._transact(f"reboot id {dxl_id}", call)
        return err

    # ---- group transactions -----------------------------------------------------------------------
    def sync_read(self, addr: int, size: int, ids: list[int], fast: bool = True,
                  retry: bool = True) -> dict[int, tuple[bytes, int]]:
        """One Sync Read (or Fast Sync Read) of ``size`` bytes at ``addr`` from every id, as one
        instruction packet. Returns ``{id: (data, status error byte)}`` (the SDK's GroupSyncRead drops
        the error bytes, which carry the alert flag, so the answers are collected here)."""
        group = sdk.GroupSyncRead(self.port, self.ph, addr, size)
        for i in ids:
            group.addParam(i)

        def call_fast():
            res = group.fastSyncReadTxPacket()
            if res != sdk.COMM_SUCCESS:
                return (res, None)
            raw, res, _ = self.ph.fastSyncReadRx(self.port, sdk.BROADCAST_ID, (size + 4) * len(ids))
            if res != sdk.COMM_SUCCESS:
                return (res, None)
            out, k = {}, 0
            for i in ids:  # ERR ID DATA CRC per device, in request order
                if len(raw) < k + size + 4 or raw[k + 1] != i:
                    return (sdk.COMM_RX_CORRUPT, None)
                out[i] = (bytes(raw[k + 2:k + 2 + size]), raw[k])
                k += size + 4
            return (sdk.COMM_SUCCESS, out)

        def call_plain():
            res = group.txPacket()
            if res != sdk.COMM_SUCCESS:
                return (res, None)
            out = {}
            for i in ids:
                data, res, err = self.ph.readRx(self.port, i, size)
                if res != sdk.COMM_SUCCESS:
                    return (res, None)
                out[i] = (bytes(data), err)
            return (sdk.COMM_SUCCESS, out)

        name = "fast sync read" if fast else "sync read"
        (out,) = self._transact(f"{name} address {addr} ids {ids}", call_fast if fast else call_plain, retry)
        return out

    def sync_write(self, addr: int, size: int, values: dict[int, int | bytes]) -> None:
        """One Sync Write (broadcast, no status: a refused item shows only when read back)."""
        group = sdk.GroupSyncWrite(self.port, self.ph, addr, size)
        for i, v in values.items():
            data = v if isinstance(v, bytes | bytearray) else (int(v) & ((1 << (8 * size)) - 1)).to_bytes(size,
                                                                                                        "little")
            if len(data) != size:
                raise ValueError(f"sync write address {addr}: {len(data)} bytes for id {i}, expected {size}")
            group.addParam(i, list(data))

        def call():
            return (group.txPacket(),)
        self._transact(f"sync write address {addr}", call)


def unpack(data: bytes, signed: bool = True) -> int:
    return int.from_bytes(data, "little", signed=signed)
