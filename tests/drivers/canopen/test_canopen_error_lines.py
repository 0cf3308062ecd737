"""A CANopen fault prints ONE error line ("CANopen errors printed twice"): ``station run`` in its
own process on the demo cell, the drives behind a socketcand hub (python-can's real client), a fault staged from
the world file. stderr must hold exactly one ``station: error:`` line, exit 2, and the fault's text nowhere else
(the driver's latch and teardown used to repeat it as warnings)."""

from __future__ import annotations

import pytest
from clirunner import station_proc
from faultrig import demo_cell

FAULTS = {  # world-file fault -> text the one error line must carry
    "EMCY": ({"do": "device_fault", "device": 3, "code": 0x2310, "at": {"pdo": {"node": 3}}}, "EMCY 0x2310"),
    "error frames": ({"do": "corrupt", "device": 3, "count": 4, "at": {"pdo": {"node": 3}}}, "CAN error frames"),
}


@pytest.mark.parametrize("fault", list(FAULTS))
def test_a_canopen_fault_prints_one_error_line(tmp_path, fault):
    entry, text = FAULTS[fault]

    def stage(doc):
        doc["faults"] = [entry]

    with demo_cell("canopen", tmp_path, 5, cross_process=True, world_doc=stage) as cell:
        r = station_proc("run", "zero_offsets", "--robot", cell.url, "--serial", cell.serial, "--cell",
                         cell.cell_path, "--db", cell.db, "-q", env=cell.env)
        assert cell.world.faults.fired, "the staged fault never reached the wire"
    assert r.code == 2, r.err
    lines = r.errors
    assert len(lines) == 1, r.err
    assert text in lines[0], r.err
    assert sum(text in x for x in r.err.splitlines()) == 1, r.err  # said once, not echoed by warnings
    assert "Traceback" not in r.err
