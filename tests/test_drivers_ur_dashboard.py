"""``station.drivers.ur.dashboard``: the dashboard server client (UR "Dashboard Server e-Series" manual: one
line per command on port 29999) against the UR controller emulator in its own process."""

from __future__ import annotations

import pytest
from station.drivers.ur.dashboard import DashboardClient
from station.mocks.world import default_doc

from station.robot.errors import ConnectionLost


def test_identity_queries_and_a_closed_server(tmp_path, emulators):
    import yaml

    doc = default_doc("ur5e", seed=3)
    doc["buses"] = {"ur": {"serial": "20235500042"}}
    world = tmp_path / "w.yaml"
    world.write_text(yaml.safe_dump(doc))
    emu = emulators("ur", world)
    c = DashboardClient(emu.host)
    try:
        c.connect()
        assert c.banner.startswith("Connected: Universal Robots Dashboard Server")
        assert c.robot_model() == "UR5"
        assert c.polyscope_version().startswith("URSoftware 5.")
        assert c.serial_number() == "20235500042"
        assert c.safety_status().startswith("Safetystatus: ")
    finally:
        c.close()
    emu.close()
    with pytest.raises(ConnectionLost, match=f"ur://{emu.host}: dashboard server {emu.host}:29999 not reachable"):
        DashboardClient(emu.host, timeout=1.0).connect()
