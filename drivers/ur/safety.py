"""What the controller's RTDE outputs ``safety_status_bits`` and ``robot_mode`` say, in the driver's words: which
bits are a stop the station must not drive through, and the robot modes by name (UR's RTDE guide, output table;
ur_rtde's ``SafetyStatus`` / ``RobotMode``)."""

from __future__ import annotations

from station.robot.errors import SafetyStop

SS_PROTECTIVE, SS_SAFEGUARD, SS_ESTOP_MASK = 1 << 2, 1 << 4, (1 << 5) | (1 << 6) | (1 << 7)
SS_VIOLATION, SS_FAULT = 1 << 8, 1 << 9
SS_HALTED = SS_PROTECTIVE | SS_ESTOP_MASK | SS_SAFEGUARD  # already halted by the safety system
ROBOT_MODE_POWER_OFF, ROBOT_MODE_POWER_ON, ROBOT_MODE_IDLE, ROBOT_MODE_RUNNING = 3, 4, 5, 7
ROBOT_MODE_BOOTING = 2
ROBOT_MODES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
               4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE"}


def mode_name(mode: int) -> str:
    return ROBOT_MODES.get(mode, str(mode))


def safety_error(host: str, bits: int) -> SafetyStop | None:
    """The stop ``safety_status_bits`` report, as the one line a technician acts on; None when there is none."""
    if bits & SS_ESTOP_MASK:
        return SafetyStop(f"ur://{host}: emergency stop (safety_status_bits 0x{bits:x}); release the "
                          "e-stop, power on and restart")
    if bits & SS_PROTECTIVE:
        return SafetyStop(f"ur://{host}: protective stop (safety_status_bits 0x{bits:x}): the robot halted. "
                          "Inspect the cause, unlock it on the teach pendant (allowed 5 s after "
                          "the stop), then resume the session")
    if bits & SS_SAFEGUARD:
        return SafetyStop(f"ur://{host}: safeguard stop (safety_status_bits 0x{bits:x}); close the guard")
    if bits & (SS_VIOLATION | SS_FAULT):
        return SafetyStop(f"ur://{host}: safety system fault/violation (safety_status_bits 0x{bits:x})")
    return None
