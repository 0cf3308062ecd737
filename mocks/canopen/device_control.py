"""The CiA 402 device control state machine as the emulated drive runs it: the states (names as
``canopen.profiles.p402`` spells them), the statusword bits each state shows, and which controlword command
moves which state where, with CiA 402's transition numbers. Source: python-canopen's
``canopen/profiles/p402.py`` (its controlword command and transition tables, which ``BaseNode402`` drives from
the master side); not re-read from the standard itself (docs/hardware-canopen.md, conformance table)."""

from __future__ import annotations

# 402 states and their statusword bits (incl. voltage enabled, bit 4, from READY TO SWITCH ON on)
NOT_READY, SOD, RTSO, SO, OE, QSA, FRA, FAULT = (
    "NOT READY TO SWITCH ON", "SWITCH ON DISABLED", "READY TO SWITCH ON", "SWITCHED ON",
    "OPERATION ENABLED", "QUICK STOP ACTIVE", "FAULT REACTION ACTIVE", "FAULT")
STATE_BITS = {NOT_READY: 0x0000, SOD: 0x0040, RTSO: 0x0031, SO: 0x0033, OE: 0x0037, QSA: 0x0017,
              FRA: 0x001F, FAULT: 0x0018}
SW_REMOTE, SW_TARGET_REACHED, SW_LIMIT, SW_SETPOINT_ACK = 1 << 9, 1 << 10, 1 << 11, 1 << 12
SW_HOMING_ATTAINED, SW_HOMING_ERROR = 1 << 12, 1 << 13  # the same bits in homing mode (CiA 402 homing)
CW_NEW_SETPOINT, CW_IMMEDIATE, CW_RELATIVE, CW_FAULT_RESET, CW_HALT = 0x10, 0x20, 0x40, 0x80, 0x100
CW_HOMING_START = 0x10  # bit 4 in homing mode: a rising edge starts the homing

DISABLE_VOLTAGE, QUICK_STOP, SHUTDOWN, SWITCH_ON, ENABLE_OPERATION = (
    "disable voltage", "quick stop", "shutdown", "switch on", "enable operation")

# (command, state) -> the state it leads to (CiA 402 transition numbers); a command not listed for a state
# changes nothing. "switch on" (0x07) in OPERATION ENABLED is the "disable operation" command.
TRANSITIONS: dict[tuple[str, str], str] = {
    (DISABLE_VOLTAGE, RTSO): SOD, (DISABLE_VOLTAGE, SO): SOD, (DISABLE_VOLTAGE, OE): SOD,  # 7, 10, 9
    (DISABLE_VOLTAGE, QSA): SOD,  # 12
    (QUICK_STOP, OE): QSA, (QUICK_STOP, RTSO): SOD, (QUICK_STOP, SO): SOD,  # 11, 7, 10
    (SHUTDOWN, SOD): RTSO, (SHUTDOWN, SO): RTSO, (SHUTDOWN, OE): RTSO,  # 2, 6, 8
    (SWITCH_ON, RTSO): SO, (SWITCH_ON, OE): SO,  # 3, 5
    (ENABLE_OPERATION, SO): OE, (ENABLE_OPERATION, RTSO): OE, (ENABLE_OPERATION, QSA): OE,  # 4, 3+4, 16
}


def command(cw: int) -> str | None:
    """The device control command a controlword carries (bits 0-3 and 7), None for none: a fault reset is
    acted on only in FAULT (the caller's), elsewhere it is ignored."""
    if cw & CW_FAULT_RESET:
        return None
    if cw & 0x02 == 0:
        return DISABLE_VOLTAGE
    if cw & 0x06 == 0x02:
        return QUICK_STOP
    if cw & 0x07 == 0x06:
        return SHUTDOWN
    if cw & 0x0F == 0x07:
        return SWITCH_ON
    if cw & 0x0F == 0x0F:
        return ENABLE_OPERATION
    return None


def next_state(state: str, cw: int) -> str | None:
    """Where ``cw`` takes a drive in ``state`` (outside FAULT), None when it stays."""
    return TRANSITIONS.get((command(cw), state))
