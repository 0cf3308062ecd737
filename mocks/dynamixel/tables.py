"""Control tables of the emulated devices (addresses, sizes, access, area, defaults, ranges).

From the ROBOTIS e-manual for XM430-W350 (model 1020) and XL430-W250 (model 1060), firmware 46-style
tables; only items a calibration station or the SDK examples touch are defined, the rest of the address
space reads as 0 and refuses writes (access error), as reserved addresses do on the real servo.

The contact sensor (model 0x5A01 = 23041) is this project's own device: a small Protocol 2.0 slave that
reports a touch/contact input (needle or seated socket) on the servo bus, see docs/hardware-dynamixel.md."""

from __future__ import annotations

from dataclasses import dataclass

EEPROM, RAM = "eeprom", "ram"
R, RW = "r", "rw"


@dataclass(frozen=True)
class Field:
    name: str
    addr: int
    size: int
    access: str = RW
    area: str = RAM
    default: int = 0
    lo: int | None = None
    hi: int | None = None

    @property
    def signed(self) -> bool:
        return self.lo is not None and self.lo < 0


@dataclass(frozen=True)
class DeviceType:
    name: str
    model_number: int
    firmware: int
    fields: tuple[Field, ...]
    size: int  # bytes of address space
    modes: tuple[int, ...] = ()  # supported operating modes
    drive_mode_bits: int = 0  # Drive Mode (10) bits this model has (the others are "unused, always 0")
    stall_torque: float = 0.0  # N m at 12 V (e-Manual specifications)
    stall_current: float = 0.0  # A at 12 V; 0: no current sensing (Present Load in 0.1 % of stall torque instead)

    def field(self, name: str) -> Field:
        for f in self.fields:
            if f.name == name:
                return f
        raise KeyError(name)

    def at(self) -> dict[int, Field]:
        return {f.addr: f for f in self.fields}


def _common_eeprom(model: int, fw: int) -> list[Field]:
    return [
        Field("model_number", 0, 2, R, EEPROM, model),
        Field("model_information", 2, 4, R, EEPROM, 0),
        Field("firmware_version", 6, 1, R, EEPROM, fw),
        Field("id", 7, 1, RW, EEPROM, 1, 0, 252),
        Field("baud_rate", 8, 1, RW, EEPROM, 1, 0, 7),
        Field("return_delay_time", 9, 1, RW, EEPROM, 250, 0, 254),
    ]


def _x_series(name: str, model: int, fw: int, *, current: bool, velocity_limit: int,
              modes: tuple[int, ...], stall: tuple[float, float]) -> DeviceType:
    f = _common_eeprom(model, fw) + [
        Field("drive_mode", 10, 1, RW, EEPROM, 0, 0, 255),  # the model's bits only: Device.check_write
        Field("operating_mode", 11, 1, RW, EEPROM, 3, 0, 16),
        Field("secondary_id", 12, 1, RW, EEPROM, 255, 0, 255),
        Field("protocol_type", 13, 1, RW, EEPROM, 2, 1, 2),
        Field("homing_offset", 20, 4, RW, EEPROM, 0, -1044479, 1044479),
        Field("moving_threshold", 24, 4, RW, EEPROM, 10, 0, 1023),
        Field("temperature_limit", 31, 1, RW, EEPROM, 80 if current else 72, 0, 100),
        Field("max_voltage_limit", 32, 2, RW, EEPROM, 160 if current else 140, 60, 160),
        Field("min_voltage_limit", 34, 2, RW, EEPROM, 95 if current else 60, 60, 160),
        Field("pwm_limit", 36, 2, RW, EEPROM, 885, 0, 885),
        Field("velocity_limit", 44, 4, RW, EEPROM, velocity_limit, 0, 1023),
        Field("max_position_limit", 48, 4, RW, EEPROM, 4095, 0, 4095),
        Field("min_position_limit", 52, 4, RW, EEPROM, 0, 0, 4095),
        Field("shutdown", 63, 1, RW, EEPROM, 52, 0, 255),
        Field("torque_enable", 64, 1, RW, RAM, 0, 0, 1),
        Field("led", 65, 1, RW, RAM, 0, 0, 1),
        Field("status_return_level", 68, 1, RW, RAM, 2, 0, 2),
        Field("registered_instruction", 69, 1, R, RAM, 0),
        Field("hardware_error_status", 70, 1, R, RAM, 0),
        Field("velocity_i_gain", 76, 2, RW, RAM, 1920, 0, 16383),
        Field("velocity_p_gain", 78, 2, RW, RAM, 100, 0, 16383),
        Field("position_d_gain", 80, 2, RW, RAM, 0, 0, 16383),
        Field("position_i_gain", 82, 2, RW, RAM, 0, 0, 16383),
        Field("position_p_gain", 84, 2, RW, RAM, 800 if current else 640, 0, 16383),
        Field("feedforward_2nd_gain", 88, 2, RW, RAM, 0, 0, 16383),
        Field("feedforward_1st_gain", 90, 2, RW, RAM, 0, 0, 16383),
        Field("bus_watchdog", 98, 1, RW, RAM, 0, 0, 127),
        Field("goal_pwm", 100, 2, RW, RAM, 885, -885, 885),
        Field("goal_velocity", 104, 4, RW, RAM, 0, -1023, 1023),
        Field("profile_acceleration", 108, 4, RW, RAM, 0, 0, 32767),
        Field("profile_velocity", 112, 4, RW, RAM, 0, 0, 32767),
        Field("goal_position", 116, 4, RW, RAM, 0, -1048575, 1048575),
        Field("realtime_tick", 120, 2, R, RAM, 0),
        Field("moving", 122, 1, R, RAM, 0),
        Field("moving_status", 123, 1, R, RAM, 0),
        Field("present_pwm", 124, 2, R, RAM, 0, -885, 885),
        Field("present_current" if current else "present_load", 126, 2, R, RAM, 0, -32768, 32767),
        Field("present_velocity", 128, 4, R, RAM, 0, -2**31, 2**31 - 1),
        Field("present_position", 132, 4, R, RAM, 0, -2**31, 2**31 - 1),
        Field("velocity_trajectory", 136, 4, R, RAM, 0, -2**31, 2**31 - 1),
        Field("position_trajectory", 140, 4, R, RAM, 0, -2**31, 2**31 - 1),
        Field("present_input_voltage", 144, 2, R, RAM, 120 if current else 115),
        Field("present_temperature", 146, 1, R, RAM, 30),
    ]
    if current:
        f += [Field("current_limit", 38, 2, RW, EEPROM, 1193, 0, 1193),
              Field("goal_current", 102, 2, RW, RAM, 1193, -1193, 1193)]
    # Drive Mode bits of the X430 series: 0 reverse, 2 time-based profile (firmware 42+), 3 torque on by goal
    # update (firmware 45+); bit 1 (dual joint master/slave) exists on X540 only
    return DeviceType(name, model, fw, tuple(sorted(f, key=lambda x: x.addr)), 147, modes, 0x0D,
                      stall[0], stall[1] if current else 0.0)


# stall torque / current at 12 V from the e-Manual specifications (XM430-W350: 4.1 N m at 2.3 A; XL430-W250:
# 1.5 N m at 1.4 A, no current sensing: Present Load in 0.1 % instead)
XM430_W350 = _x_series("XM430-W350", 1020, 46, current=True, velocity_limit=200, modes=(0, 1, 3, 4, 5, 16),
                       stall=(4.1, 2.3))
XL430_W250 = _x_series("XL430-W250", 1060, 46, current=False, velocity_limit=265, modes=(1, 3, 4, 16),
                       stall=(1.5, 1.4))

CONTACT_SENSOR = DeviceType(
    "STATION-CONTACT", 0x5A01, 1,
    tuple(_common_eeprom(0x5A01, 1) + [
        Field("led", 65, 1, RW, RAM, 0, 0, 1),
        Field("status_return_level", 68, 1, RW, RAM, 2, 0, 2),
        Field("realtime_tick", 120, 2, R, RAM, 0),
        Field("contact", 128, 1, R, RAM, 0),  # 1 while the tool tip touches a needle / sits in a socket
        Field("contact_count", 129, 2, R, RAM, 0),  # rising edges since power-on (wraps at 65536)
    ]),
    131,
)

DEVICE_TYPES = {t.model_number: t for t in (XM430_W350, XL430_W250, CONTACT_SENSOR)}
BY_NAME = {"xm430": XM430_W350, "xm430-w350": XM430_W350, "xl430": XL430_W250, "xl430-w250": XL430_W250}

# Protocol 2.0 status error numbers (low 7 bits) and the alert flag
ERR_RESULT_FAIL, ERR_INSTRUCTION, ERR_CRC, ERR_DATA_RANGE, ERR_DATA_LENGTH, ERR_DATA_LIMIT, ERR_ACCESS = range(1, 8)
ALERT = 0x80

# Hardware error status (address 70) bits
HW_INPUT_VOLTAGE, HW_OVERHEATING, HW_ENCODER, HW_ELECTRICAL_SHOCK, HW_OVERLOAD = 0x01, 0x04, 0x08, 0x10, 0x20

BAUD_CODES = {0: 9600, 1: 57600, 2: 115200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000, 6: 4_000_000, 7: 4_500_000}
BAUD_TO_CODE = {v: k for k, v in BAUD_CODES.items()}

# Units
VELOCITY_UNIT = 0.229 * 2 * 3.141592653589793 / 60  # rad/s per profile-velocity unit (0.229 rev/min)
ACCEL_UNIT = 214.577 * 2 * 3.141592653589793 / 3600  # rad/s^2 per profile-acceleration unit (214.577 rev/min^2)
CURRENT_UNIT = 2.69e-3  # A per goal/present current unit (XM430)
COMPLIANT_CURRENT = 100  # goal current (units) at or below which mode 5 counts as compliant (~0.27 A)
COMPLIANT_PWM = 110  # goal PWM (units of 0.113 %) at or below which a position mode counts as compliant (~12 %)
LOAD_UNIT = 1e-3  # Present Load (XL430, no current sensing): 0.1 % of the stall torque per unit
ONE_TURN = 4096  # Present Position ticks per turn (12-bit absolute encoder)
HOMING_OFFSET_POSITION_MODE = 1024  # Position Control Mode ignores homing offsets beyond this (e-Manual)
DRIVE_REVERSE, DRIVE_SLAVE, DRIVE_TIME_PROFILE, DRIVE_TORQUE_ON_GOAL = 0x01, 0x02, 0x04, 0x08
MODE_POSITION = 3
