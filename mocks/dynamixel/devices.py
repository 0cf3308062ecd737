"""One emulated device: control-table memory with the servo's access rules (EEPROM lock, ranges,
read-only items, reserved addresses), hardware error latch and reboot semantics."""

from __future__ import annotations

from station.mocks.dynamixel.tables import (
    ALERT,
    DRIVE_TIME_PROFILE,
    EEPROM,
    ERR_ACCESS,
    ERR_DATA_LENGTH,
    ERR_DATA_LIMIT,
    ERR_DATA_RANGE,
    ERR_RESULT_FAIL,
    RW,
    DeviceType,
    Field,
)


class WriteRefused(Exception):
    def __init__(self, code: int, why: str) -> None:
        super().__init__(why)
        self.code = code


class Device:
    """Memory image of one device. EEPROM bytes survive ``reboot()`` and can be exported/imported to
    emulate a power cycle; RAM returns to defaults."""

    def __init__(self, dtype: DeviceType, dxl_id: int, eeprom: bytes | None = None, *, baud_code: int = 3,
                 return_delay: int | None = None) -> None:
        self.type = dtype
        self.mem = bytearray(dtype.size)
        self._by_addr: list[Field | None] = [None] * dtype.size
        for f in dtype.fields:
            for a in range(f.addr, f.addr + f.size):
                self._by_addr[a] = f
        for f in dtype.fields:
            self._store(f, f.default)
        self._store(dtype.field("id"), dxl_id)
        self._store(dtype.field("baud_rate"), baud_code)
        if return_delay is not None:
            self._store(dtype.field("return_delay_time"), return_delay)
        if eeprom is not None:
            self.load_eeprom(eeprom)
        self.registered: tuple[int, bytes] | None = None  # REG_WRITE pending until ACTION

    # ---- raw memory -----------------------------------------------------------------------
    def _store(self, f: Field, value: int) -> None:
        self.mem[f.addr:f.addr + f.size] = int(value).to_bytes(f.size, "little", signed=value < 0)

    def get(self, name: str) -> int:
        f = self.type.field(name)
        return int.from_bytes(self.mem[f.addr:f.addr + f.size], "little", signed=f.signed)

    def set(self, name: str, value: int) -> None:
        """Device-internal update (present values, error latch): no access checks."""
        f = self.type.field(name)
        if f.size < 4 and not f.signed:
            value = int(value) & ((1 << (8 * f.size)) - 1)
        self._store(f, int(value))

    def has(self, name: str) -> bool:
        return any(f.name == name for f in self.type.fields)

    @property
    def dxl_id(self) -> int:
        return self.mem[7]

    @property
    def torque(self) -> bool:
        return self.has("torque_enable") and bool(self.get("torque_enable"))

    @property
    def hardware_error(self) -> int:
        return self.get("hardware_error_status") if self.has("hardware_error_status") else 0

    @property
    def error_flags(self) -> int:
        """Error byte of every status packet: the alert bit while a hardware error is latched."""
        return ALERT if self.hardware_error else 0

    # ---- EEPROM persistence ---------------------------------------------------------------
    def eeprom(self) -> bytes:
        return bytes(self.mem[:64])

    def load_eeprom(self, data: bytes) -> None:
        for f in self.type.fields:
            if f.area == EEPROM and f.access == RW and f.addr + f.size <= len(data):
                self.mem[f.addr:f.addr + f.size] = data[f.addr:f.addr + f.size]

    # ---- instruction-level access ---------------------------------------------------------
    def read(self, addr: int, length: int) -> bytes:
        if length < 1 or addr < 0 or addr + length > self.type.size:
            raise WriteRefused(ERR_ACCESS, f"read {addr}+{length} outside the control table")
        return bytes(self.mem[addr:addr + length])

    def check_write(self, addr: int, data: bytes) -> list[tuple[Field, int]]:
        """Validate a write without applying it; returns the (field, value) pairs to apply."""
        if not data or addr < 0 or addr + len(data) > self.type.size:
            raise WriteRefused(ERR_ACCESS, f"write {addr}+{len(data)} outside the control table")
        out: list[tuple[Field, int]] = []
        a = addr
        end = addr + len(data)
        while a < end:
            f = self._writable_field(a, end)
            value = int.from_bytes(data[a - addr:a - addr + f.size], "little", signed=f.signed)
            self._check_range(f, value)
            out.append((f, self._check_state(f, value)))
            a += f.size
        return out

    def _writable_field(self, a: int, end: int) -> Field:
        """The field a write to ``a`` (ending before ``end``) stores into: a whole RW field, EEPROM only with
        torque off."""
        f = self._by_addr[a]
        if f is None or f.access != RW:
            raise WriteRefused(ERR_ACCESS, f"address {a} is read-only or reserved")
        if f.addr != a or f.addr + f.size > end:
            raise WriteRefused(ERR_DATA_LENGTH, f"write covers only part of {f.name} ({f.addr}+{f.size})")
        if f.area == EEPROM and self.torque:
            raise WriteRefused(ERR_ACCESS, f"{f.name} is in EEPROM: torque must be off to write it")
        return f

    def _check_range(self, f: Field, value: int) -> None:
        """The values a field takes at all: its range, the model's operating modes and drive mode bits, the
        time-based profile's range."""
        if (f.lo is not None and value < f.lo) or (f.hi is not None and value > f.hi):
            raise WriteRefused(ERR_DATA_RANGE, f"{f.name}={value} outside [{f.lo}, {f.hi}]")
        if f.name == "operating_mode" and self.type.modes and value not in self.type.modes:
            raise WriteRefused(ERR_DATA_RANGE, f"operating mode {value} not supported by {self.type.name}")
        unused = value & ~self.type.drive_mode_bits if f.name == "drive_mode" else 0
        if unused:
            raise WriteRefused(ERR_DATA_RANGE, f"drive mode 0x{value:02X}: bits 0x{unused:02X} are unused on "
                               f"{self.type.name} (always 0)")
        if f.name in ("profile_velocity", "profile_acceleration") and self._time_based() and value > 32737:
            raise WriteRefused(ERR_DATA_RANGE, f"{f.name}={value} ms outside the time-based range [0, 32737]")

    def _time_based(self) -> bool:
        return bool(self.has("drive_mode") and self.get("drive_mode") & DRIVE_TIME_PROFILE)

    def _check_state(self, f: Field, value: int) -> int:
        """What the servo's present state allows (limits, bus watchdog, a latched hardware error); the value
        to store (a profile velocity is clamped to the velocity limit)."""
        if f.name == "goal_position" and self.get("operating_mode") == 3:
            lo, hi = self.get("min_position_limit"), self.get("max_position_limit")
            if not lo <= value <= hi:
                raise WriteRefused(ERR_DATA_LIMIT, f"goal {value} outside position limits [{lo}, {hi}]")
        if f.name == "goal_current" and abs(value) > self.get("current_limit"):
            raise WriteRefused(ERR_DATA_LIMIT, f"goal current {value} above current limit")
        if f.name == "profile_velocity" and not self._time_based() and value > self.get("velocity_limit") > 0:
            value = self.get("velocity_limit")  # the profile is clamped to the velocity limit
        if f.name == "goal_position" and self.has("bus_watchdog") and self.get("bus_watchdog") == 255:
            raise WriteRefused(ERR_RESULT_FAIL, "bus watchdog tripped: write 0 to bus watchdog (98) first")
        if f.name == "torque_enable" and value and self.hardware_error:
            raise WriteRefused(ERR_RESULT_FAIL, "hardware error latched: reboot before enabling torque")
        return value

    def apply(self, items: list[tuple[Field, int]]) -> None:
        for f, value in items:
            self._store(f, value)

    def latch_hardware_error(self, bits: int) -> None:
        """Set hardware error bits; with the shutdown mask matching, torque goes off until reboot."""
        self.set("hardware_error_status", self.hardware_error | bits)
        if self.get("shutdown") & bits and self.has("torque_enable"):
            self.set("torque_enable", 0)

    def reboot(self) -> None:
        """Power-on state: RAM to defaults (torque off, error cleared), EEPROM kept."""
        keep = self.eeprom()
        for f in self.type.fields:
            if f.area != EEPROM:
                self._store(f, f.default)
        self.load_eeprom(keep)
        self.registered = None

    def factory_reset(self, option: int) -> None:
        keep_id, keep_baud = self.get("id"), self.get("baud_rate")
        for f in self.type.fields:
            self._store(f, f.default)
        if option in (0x01, 0x02):
            self.set("id", keep_id)
        if option == 0x02:
            self.set("baud_rate", keep_baud)
