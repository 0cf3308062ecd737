"""CiA 402 (drives and motion control) as the driver uses it: controlword/statusword bits, modes of operation,
the power state machine and the controlword that moves a drive one transition towards OPERATION ENABLED."""

from __future__ import annotations

CW_SHUTDOWN, CW_SWITCH_ON, CW_ENABLE, CW_QUICK_STOP, CW_FAULT_RESET = 0x06, 0x07, 0x0F, 0x02, 0x80
CW_NEW_SETPOINT, CW_IMMEDIATE, CW_HALT = 0x10, 0x20, 0x100
CW_HOMING_START = 0x10  # bit 4 in homing mode: its rising edge starts the homing
SW_TARGET_REACHED, SW_SETPOINT_ACK = 1 << 10, 1 << 12
SW_HOMING_ATTAINED, SW_HOMING_ERROR = 1 << 12, 1 << 13  # bits 12/13 in homing mode (bit 10: not running)
MODE_PP, MODE_PT, MODE_HM = 1, 4, 6  # profile position, profile torque, homing
HOMING_CURRENT_POSITION = (37, 35)  # CiA 402 "homing on the current position": 37, and 35 in older editions
SUPPORTS_HOMING = 1 << 5  # 0x6502 supported drive modes: bit 5 homing mode
SAVE = 0x65766173  # "save" written to 0x1010 stores the parameters
STORE_APPLICATION = 3  # 0x1010:03 saves the application parameters (CiA 301: 0x6000-0x9FFF)
CONTACT_BIT = 16  # bit of 0x60FD digital inputs wired to the cell's contact input

STATES = (("NOT READY TO SWITCH ON", 0x4F, 0x00), ("SWITCH ON DISABLED", 0x4F, 0x40),
          ("READY TO SWITCH ON", 0x6F, 0x21), ("SWITCHED ON", 0x6F, 0x23), ("OPERATION ENABLED", 0x6F, 0x27),
          ("QUICK STOP ACTIVE", 0x6F, 0x07), ("FAULT REACTION ACTIVE", 0x4F, 0x0F), ("FAULT", 0x4F, 0x08))
ENABLED = "OPERATION ENABLED"
FAULTED = ("FAULT", "FAULT REACTION ACTIVE")

# controlword of the next transition towards OPERATION ENABLED; NOT READY / FAULT REACTION ACTIVE pass by themselves
_TOWARDS_ENABLED = {"FAULT": CW_FAULT_RESET, "SWITCH ON DISABLED": CW_SHUTDOWN, "READY TO SWITCH ON": CW_SWITCH_ON,
                    "SWITCHED ON": CW_ENABLE, "QUICK STOP ACTIVE": CW_ENABLE}


def state_of(sw: int) -> str:
    for name, mask, bits in STATES:
        if sw & mask == bits:
            return name
    return "UNKNOWN"


def next_controlword(state: str, last: int | None) -> int | None:
    """Controlword for a drive in ``state`` (``last``: what it got the round before), ``None``: wait.
    The fault reset acts on a rising edge: after a round with the bit set, drop it, set it again next round."""
    cw = _TOWARDS_ENABLED.get(state)
    if cw == CW_FAULT_RESET and last == CW_FAULT_RESET:
        return 0x00
    return cw
