"""The emulated drive's CiA 402 device control table against python-canopen's own (``canopen.profiles.p402``,
the master side the station's driver uses): every transition the master commands leads where the master expects,
and every state shows the statusword bits the master reads it by."""

from __future__ import annotations

from canopen.profiles.p402 import State402
from station.mocks.canopen.device_control import (
    FAULT,
    FRA,
    NOT_READY,
    STATE_BITS,
    TRANSITIONS,
    command,
    next_state,
)


def test_every_transition_the_master_commands_leads_where_it_expects():
    checked = 0
    for (state, goal), cw in State402.TRANSITIONTABLE.items():
        if state not in STATE_BITS or state in (NOT_READY, FRA, FAULT) or command(cw) is None:
            # the drive's own transitions (START, 1: NOT READY -> SWITCH ON DISABLED at power-up, the fault
            # reaction) and the fault reset, which the drive acts on only in FAULT, on its rising edge
            continue
        assert next_state(state, cw) == goal, (state, hex(cw), goal)
        checked += 1
    assert checked >= 10


def test_every_state_shows_the_statusword_bits_the_master_reads():
    for state, (mask, value) in State402.SW_MASK.items():
        assert STATE_BITS[state] & mask == value, state


def test_a_command_not_listed_for_a_state_changes_nothing():
    assert next_state("SWITCH ON DISABLED", State402.CW_OPERATION_ENABLED) is None  # 2 and 3 come first
    assert next_state("QUICK STOP ACTIVE", State402.CW_SHUTDOWN) is None
    assert command(0x80 | State402.CW_OPERATION_ENABLED) is None  # a fault reset outside FAULT is ignored
    assert all(new in STATE_BITS for new in TRANSITIONS.values())
