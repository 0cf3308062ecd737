"""``station.drivers.ur.dashboard``: the dashboard server client (UR "Dashboard Server e-Series" manual: one
line per command on port 29999) against the UR controller emulator in its own process."""

from __future__ import annotations

import pytest
from station.drivers.ur.dashboard import DashboardClient
from station.mocks.ur.server import CONTROLLER_VERSION, DASHBOARD_PORT, SAFETY_NAMES, _version_numbers
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
        version = c.polyscope_version()
        assert version.startswith("URSoftware 5.")
        # the version the dashboard states is the one the controller runs (its primary interface sends the same)
        assert _version_numbers(version) == CONTROLLER_VERSION
        assert c.serial_number() == "20235500042"
        assert c.safety_status() == f"Safetystatus: {SAFETY_NAMES[1]}"  # RTDE guide: safety_mode 1 = NORMAL
        assert c.port == DASHBOARD_PORT == 29999  # the dashboard server's port (Dashboard Server manual)
    finally:
        c.close()
    emu.close()
    with pytest.raises(ConnectionLost, match=f"ur://{emu.host}: dashboard server {emu.host}:29999 not reachable"):
        DashboardClient(emu.host, timeout=1.0).connect()
