"""The parts of the ROBOTIS X-series control table (Protocol 2.0) the driver uses, and unit scales.

Kept on the station side of the wire on purpose: the driver must not import the emulator."""

from __future__ import annotations

import math

# EEPROM (writable only with torque off)
MODEL_NUMBER, FIRMWARE_VERSION, RETURN_DELAY_TIME, OPERATING_MODE = 0, 6, 9, 11
HOMING_OFFSET, CURRENT_LIMIT, MAX_POSITION_LIMIT, MIN_POSITION_LIMIT = 20, 38, 48, 52
# RAM
TORQUE_ENABLE, HARDWARE_ERROR_STATUS, BUS_WATCHDOG, GOAL_CURRENT = 64, 70, 98, 102
PROFILE_ACCELERATION, PROFILE_VELOCITY, GOAL_POSITION = 108, 112, 116
MOVING, PRESENT_POSITION = 122, 132
# one poll of a waited move: Goal Position .. Present Position (116..135), offsets of Moving and Present Position
POLL_SIZE, POLL_MOVING, POLL_PRESENT = 20, MOVING - GOAL_POSITION, PRESENT_POSITION - GOAL_POSITION
# read-back after torque / compliance switches: 64..135, torque .. hardware error .. bus watchdog .. goal current
# .. present position
CONFIRM_SIZE = PRESENT_POSITION + 4 - TORQUE_ENABLE
# contact sensor device (this project's, model 0x5A01): 1 while the tool touches a needle / sits in a socket
CONTACT = 128

MODE_POSITION, MODE_CURRENT_POSITION = 3, 5
HOMING_OFFSET_RANGE = 1_044_479  # ticks, both signs

SERVO_MODELS = {1020: "XM430-W350", 1030: "XM430-W210", 1060: "XL430-W250", 1120: "XM540-W270",
                1130: "XM540-W150"}
# the servo each built-in model is built from (its model file's description); other models: any of SERVO_MODELS
# unless the URL says servo=...
MODEL_SERVOS = {"omx": 1020}
CURRENT_CAPABLE = {1020, 1030, 1120, 1130}  # have current-based position mode (5) and Goal Current (102)
CONTACT_SENSOR_MODEL = 0x5A01

HARDWARE_ERRORS = {0x01: "input voltage", 0x04: "overheating", 0x08: "motor encoder", 0x10: "electrical shock",
                   0x20: "overload"}
PACKET_ERRORS = {1: "result fail", 2: "instruction error", 3: "CRC error", 4: "data range error",
                 5: "data length error", 6: "data limit error", 7: "access error"}
ALERT = 0x80

VELOCITY_UNIT = 0.229 * 2 * math.pi / 60  # rad/s per profile-velocity unit (0.229 rev/min)
ACCEL_UNIT = 214.577 * 2 * math.pi / 3600  # rad/s^2 per profile-acceleration unit (214.577 rev/min^2)
WATCHDOG_UNITS = 10  # x 20 ms: servos stop by themselves if a waited-for move loses the bus for 0.2 s
COMPLIANT_GOAL_CURRENT = 60  # units of 2.69 mA: ~0.16 A, enough to hold the tip in a cone, not to push


def describe_hardware_error(bits: int) -> str:
    names = [name for bit, name in HARDWARE_ERRORS.items() if bits & bit]
    return ", ".join(names) if names else "unknown"
