"""The parts of the ROBOTIS X-series control table (Protocol 2.0) the driver uses, and unit scales.

Kept on the station side of the wire on purpose: the driver must not import the emulator."""

from __future__ import annotations

import math

# EEPROM (writable only with torque off)
MODEL_NUMBER, FIRMWARE_VERSION, RETURN_DELAY_TIME, DRIVE_MODE, OPERATING_MODE = 0, 6, 9, 10, 11
HOMING_OFFSET, PWM_LIMIT, CURRENT_LIMIT, MAX_POSITION_LIMIT, MIN_POSITION_LIMIT = 20, 36, 38, 48, 52
# RAM
TORQUE_ENABLE, STATUS_RETURN_LEVEL, HARDWARE_ERROR_STATUS, BUS_WATCHDOG = 64, 68, 70, 98
GOAL_PWM, GOAL_CURRENT, PROFILE_ACCELERATION, PROFILE_VELOCITY, GOAL_POSITION = 100, 102, 108, 112, 116
MOVING, PRESENT_CURRENT, PRESENT_POSITION = 122, 126, 132  # 126: Present Load (0.1 %) on servos without current
# one read at connect per servo: Firmware Version .. Operating Mode (6..11)
INFO_ADDR, INFO_SIZE = FIRMWARE_VERSION, OPERATING_MODE + 1 - FIRMWARE_VERSION
# one poll of a waited move: Goal Position .. Present Position (116..135), offsets of Moving and Present Position
POLL_SIZE, POLL_MOVING, POLL_PRESENT = 20, MOVING - GOAL_POSITION, PRESENT_POSITION - GOAL_POSITION
# read-back after torque / compliance switches: 64..135, torque .. hardware error .. bus watchdog .. goal current
# .. present position
CONFIRM_SIZE = PRESENT_POSITION + 4 - TORQUE_ENABLE
# contact sensor device (this project's, model 0x5A01): 1 while the tool touches a needle / sits in a socket
CONTACT = 128

MODE_POSITION, MODE_EXTENDED_POSITION, MODE_CURRENT_POSITION = 3, 4, 5
POSITION_MODES = (MODE_POSITION, MODE_EXTENDED_POSITION, MODE_CURRENT_POSITION)
MODE_NAMES = {0: "current control", 1: "velocity control", 3: "position control", 4: "extended position control",
              5: "current-based position control", 16: "PWM control"}
HOMING_OFFSET_RANGE = 1_044_479  # ticks, both signs
HOMING_OFFSET_POSITION_MODE = 1_024  # Position Control Mode ignores a homing offset beyond this (e-Manual)
ONE_TURN = 4096  # Present Position ticks per turn: the reading a servo resets to lies within one turn
# Drive Mode (10) bits: 0 reverse direction, 1 dual-joint slave (X540), 2 time-based profile (ms), 3 torque on by
# goal update
DRIVE_REVERSE, DRIVE_SLAVE, DRIVE_TIME_PROFILE, DRIVE_TORQUE_ON_GOAL = 0x01, 0x02, 0x04, 0x08
PROFILE_TIME_MAX = 32737  # ms: the time-based profile's range

SERVO_MODELS = {1020: "XM430-W350", 1030: "XM430-W210", 1060: "XL430-W250", 1120: "XM540-W270",
                1130: "XM540-W150"}
# the servo each built-in model is built from (its model file's description); other models: any of SERVO_MODELS
# unless the URL says servo=...
MODEL_SERVOS = {"omx": 1020}
CURRENT_CAPABLE = {1020, 1030, 1120, 1130}  # have current-based position mode (5) and Goal Current (102)
# stall torque (N m) and current (A) at 12 V (e-Manual specifications): Present Current (2.69 mA) -> torque; a servo
# without current sensing reports Present Load in 0.1 % of its stall torque
STALL = {1020: (4.1, 2.3), 1030: (3.0, 2.3), 1060: (1.5, 1.4), 1120: (10.6, 4.4), 1130: (7.3, 4.4)}
CURRENT_UNIT = 2.69e-3  # A
LOAD_UNIT = 1e-3  # share of the stall torque
CONTACT_SENSOR_MODEL = 0x5A01

HARDWARE_ERRORS = {0x01: "input voltage", 0x04: "overheating", 0x08: "motor encoder", 0x10: "electrical shock",
                   0x20: "overload"}
PACKET_ERRORS = {1: "result fail", 2: "instruction error", 3: "CRC error", 4: "data range error",
                 5: "data length error", 6: "data limit error", 7: "access error"}
ALERT = 0x80

VELOCITY_UNIT = 0.229 * 2 * math.pi / 60  # rad/s per profile-velocity unit (0.229 rev/min)
ACCEL_UNIT = 214.577 * 2 * math.pi / 3600  # rad/s^2 per profile-acceleration unit (214.577 rev/min^2)
WATCHDOG_UNITS = 10  # x 20 ms: servos stop by themselves if a waited-for move loses the bus for 0.2 s
# compliance: Goal PWM (100, RAM) limits the output in every position mode (e-Manual, Goal PWM): no mode switch, so
# the torque never goes off (a DYNAMIXEL has no brake). 90 of 885 = 10 %: about 0.4 N m at stall on an XM430-W350
COMPLIANT_GOAL_PWM = 90


def describe_hardware_error(bits: int) -> str:
    names = [name for bit, name in HARDWARE_ERRORS.items() if bits & bit]
    return ", ".join(names) if names else "unknown"
