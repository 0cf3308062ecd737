"""``station.drivers.dynamixel.table`` (the driver's view of the X-series control table) against the emulator's
control tables (``station.mocks.dynamixel.tables``): two copies written from the ROBOTIS e-Manual on the two sides
of the wire must agree on every address, the stall data and the profile units."""

from __future__ import annotations

import math

import pytest
from station.drivers.dynamixel import table as T
from station.mocks.dynamixel.tables import ACCEL_UNIT, BY_NAME, CONTACT_SENSOR, DEVICE_TYPES, VELOCITY_UNIT

ADDRESSES = {  # driver name -> emulator field
    "MODEL_NUMBER": "model_number", "FIRMWARE_VERSION": "firmware_version", "RETURN_DELAY_TIME": "return_delay_time",
    "DRIVE_MODE": "drive_mode", "OPERATING_MODE": "operating_mode", "HOMING_OFFSET": "homing_offset",
    "PWM_LIMIT": "pwm_limit", "MAX_POSITION_LIMIT": "max_position_limit", "MIN_POSITION_LIMIT": "min_position_limit",
    "TORQUE_ENABLE": "torque_enable", "STATUS_RETURN_LEVEL": "status_return_level",
    "HARDWARE_ERROR_STATUS": "hardware_error_status", "BUS_WATCHDOG": "bus_watchdog", "GOAL_PWM": "goal_pwm",
    "PROFILE_ACCELERATION": "profile_acceleration", "PROFILE_VELOCITY": "profile_velocity",
    "GOAL_POSITION": "goal_position", "MOVING": "moving", "PRESENT_POSITION": "present_position",
}


@pytest.mark.parametrize("servo", ["xm430", "xl430"])
def test_addresses_agree_with_the_emulated_servos(servo):
    dev = BY_NAME[servo]
    for const, name in ADDRESSES.items():
        assert getattr(T, const) == dev.field(name).addr, const
    assert T.HOMING_OFFSET_RANGE == dev.field("homing_offset").hi == -dev.field("homing_offset").lo
    assert dev.model_number in T.SERVO_MODELS
    assert T.STALL[dev.model_number] == (dev.stall_torque, dev.stall_current or T.STALL[dev.model_number][1])
    assert set(dev.modes) <= set(T.MODE_NAMES)


def test_current_items_and_the_contact_sensor():
    xm = DEVICE_TYPES[1020]
    assert xm.field("goal_current").addr == T.GOAL_CURRENT and xm.field("present_current").addr == T.PRESENT_CURRENT
    assert 1020 in T.CURRENT_CAPABLE and 1060 not in T.CURRENT_CAPABLE
    assert CONTACT_SENSOR.model_number == T.CONTACT_SENSOR_MODEL
    assert any(f.addr == T.CONTACT for f in CONTACT_SENSOR.fields)


def test_units_and_read_blocks():
    assert T.VELOCITY_UNIT == pytest.approx(VELOCITY_UNIT) == pytest.approx(0.229 * 2 * math.pi / 60)
    assert pytest.approx(ACCEL_UNIT) == T.ACCEL_UNIT
    # the poll block reads Goal Position .. Present Position inclusive (4 bytes at 132)
    assert T.GOAL_POSITION + T.POLL_SIZE == T.PRESENT_POSITION + 4 and T.POLL_PRESENT == 16
    assert T.describe_hardware_error(0x24) == "overheating, overload" and T.describe_hardware_error(0) == "unknown"
