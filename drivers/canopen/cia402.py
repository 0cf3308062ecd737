"""CiA 402 (drives and motion control) as the driver uses it: controlword/statusword bits, modes of operation,
the power state machine and the controlword that moves a drive one transition towards OPERATION ENABLED."""

from __future__ import annotations

CW_SHUTDOWN, CW_SWITCH_ON, CW_ENABLE, CW_QUICK_STOP, CW_FAULT_RESET = 0x06, 0x07, 0x0F, 0x02, 0x80
CW_NEW_SETPOINT, CW_IMMEDIATE, CW_HALT = 0x10, 0x20, 0x100
SW_TARGET_REACHED, SW_SETPOINT_ACK = 1 << 10, 1 << 12
MODE_PP, MODE_PT = 1, 4  # profile position, profile torque
COMPLIANT_TORQUE = 50  # per mille of rated torque while seating in a socket
SAVE = 0x65766173  # "save" written to 0x1010 stores the parameters
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
