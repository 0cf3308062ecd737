"""Controller-side constants and the register bank an emulated UR controller shares between its ports."""

from __future__ import annotations

# runtime_state (RTDE guide)
STOPPING, STOPPED, PLAYING, PAUSING, PAUSED, RESUMING = range(6)

# robot_mode (RTDE guide; the dashboard's "robotmode" names them)
ROBOT_MODE_POWER_OFF, ROBOT_MODE_POWER_ON, ROBOT_MODE_IDLE, ROBOT_MODE_RUNNING = 3, 4, 5, 7

# safety_mode
SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP, SAFETY_ROBOT_EMERGENCY_STOP = 1, 3, 7

# robot_status_bits
RS_POWER_ON, RS_PROGRAM_RUNNING, RS_TEACH_BUTTON, RS_POWER_BUTTON = (1 << i for i in range(4))

# safety_status_bits
SS_NORMAL = 1 << 0
SS_REDUCED = 1 << 1
SS_PROTECTIVE_STOPPED = 1 << 2
SS_RECOVERY = 1 << 3
SS_SAFEGUARD_STOPPED = 1 << 4
SS_SYSTEM_EMERGENCY_STOPPED = 1 << 5
SS_ROBOT_EMERGENCY_STOPPED = 1 << 6
SS_EMERGENCY_STOPPED = 1 << 7
SS_VIOLATION = 1 << 8
SS_FAULT = 1 << 9
SS_STOPPED_DUE_TO_SAFETY = 1 << 10

# actual_digital_input_bits: 0-7 standard DI, 8-15 configurable, 16-17 tool inputs.
# The contact sensor (needle / seated-in-socket switch) is wired to tool digital input 0 by default.
DEFAULT_CONTACT_BIT = 16

# Command ids of the control script ur_rtde 1.6.x uploads (input_int_register_0), learned by reading the
# script the client sends to port 30003 (``station mock ur --dump-script FILE`` writes it out).
CMD_NONE = 0
CMD_MOVEJ = 1
CMD_MOVEJ_IK = 2
CMD_MOVEL = 3
CMD_MOVEL_FK = 4
CMD_FORCE_MODE = 6
CMD_FORCE_MODE_STOP = 7
CMD_ZERO_FT_SENSOR = 8
CMD_SPEEDJ = 9
CMD_SPEEDL = 10
CMD_SERVOJ = 11
CMD_SERVOC = 12
CMD_SPEED_STOP = 15
CMD_SERVO_STOP = 16
CMD_SET_PAYLOAD = 17
CMD_TEACH_MODE = 18
CMD_END_TEACH_MODE = 19
CMD_FORCE_MODE_SET_DAMPING = 20
CMD_FORCE_MODE_SET_GAIN_SCALING = 21
CMD_SERVOL = 24
CMD_TOOL_CONTACT = 25
CMD_GET_STEPTIME = 26
CMD_GET_ACTUAL_JOINT_POSITIONS_HISTORY = 27
CMD_SET_TCP = 29
CMD_GET_INVERSE_KINEMATICS_ARGS = 30
CMD_PROTECTIVE_STOP = 31
CMD_STOPL = 33
CMD_STOPJ = 34
CMD_SET_WATCHDOG = 35
CMD_IS_POSE_WITHIN_SAFETY_LIMITS = 36
CMD_IS_JOINTS_WITHIN_SAFETY_LIMITS = 37
CMD_GET_JOINT_TORQUES = 38
CMD_GET_TCP_OFFSET = 40
CMD_JOG_START = 41
CMD_JOG_STOP = 42
CMD_GET_FORWARD_KINEMATICS_DEFAULT = 43
CMD_GET_FORWARD_KINEMATICS_ARGS = 44
CMD_GET_INVERSE_KINEMATICS_DEFAULT = 46
CMD_IS_STEADY = 47
CMD_FREEDRIVE_MODE = 52
CMD_END_FREEDRIVE_MODE = 53
CMD_GET_FREEDRIVE_STATUS = 54
CMD_SET_TARGET_PAYLOAD = 65
CMD_WATCHDOG = 99
CMD_STOP_SCRIPT = 255

# Commands the script's main loop handles without the done-handshake (it signals "ready" right away).
REALTIME_COMMANDS = frozenset({24, 11, 9, 10, 6, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71, CMD_WATCHDOG})

# output_int_register_0 values the script writes
SCRIPT_READY = 1
SCRIPT_DONE = 2
