"""The jog UI on the other bus: an emulated Dynamixel arm on a pty (real dynamixel_sdk), opened through the
`station jog` glue (`open_jog`: URL, model, session folder under STATION_HOME)."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from station.mocks.dynamixel import DynamixelEmulator
from station.mocks.world import World
from station.mocks.world.cell import DEFAULTS

from station.cli.jog_cmd import open_jog
from station.engine.journal import read_journal
from station.samplesfile import read_samples
from station.tui.app import JogApp

START = [0.2, -0.3, 0.4, 0.1]


pytestmark = pytest.mark.usefixtures("tui_no_idle_wait")  # see tests/conftest.py


@pytest.fixture
def rig(tmp_path, monkeypatch):
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    # the servos resolve 0.088 deg (~0.3 mm at the tip): a 1.5 mm contact radius lets a commanded pose touch
    cell = {"contact_radius": 0.0015, "points": DEFAULTS["omx"]["points"]}
    world = World.default(model="omx", seed=4, start=START, cell=cell,
                          errors={"explicit": {"offset.j2": 0.01, "offset.j3": -0.008}})
    emu = DynamixelEmulator(world, ids=[11, 12, 13, 14])
    path = emu.start().path
    robot, ctl = open_jog(f"dynamixel://{path}?baud=1000000&ids=11-14&contact=200", model="omx",
                          identify="offsets", serial="OMX-7")
    yield world, robot, ctl
    ctl.close()
    robot.close()
    emu.stop()


def tick(model) -> np.ndarray:
    return np.array([1.0 / (j.encoder.counts_per_unit * j.encoder.gear) for j in model.joints])


def test_jog_record_and_fault_on_dynamixel(rig, tmp_path):
    world, robot, ctl = rig
    one = tick(world.nominal)
    assert ctl.session.folder.parent == tmp_path / "home" / "sessions"
    needle = world.points["N"].position
    q_touch = world.truth.ik(needle, np.array(START), position_only=True).q[0]

    async def run():
        app = JogApp(ctl, poll_s=0.1)
        async with app.run_test(size=(150, 50)) as pilot:
            assert "disabled" in str(app.query_one("#jog").render())  # torque off after connect
            await pilot.press("c")  # enable
            assert robot.status().enabled and ctl.fault is None
            q0 = world.encoder_q()
            await pilot.press("3", "w")  # J2 +1 deg
            await pilot.pause(0.05)
            d = world.encoder_q() - q0
            assert d[1] == pytest.approx(np.deg2rad(1.0), abs=one[1])
            assert np.all(np.abs(d[[0, 2, 3]]) <= one[[0, 2, 3]])
            # Cartesian X +1 mm: the nominal tip moves 1 mm, up to the servos' tick quantisation at both ends
            q0 = world.encoder_q()
            await pilot.press("m", "q")
            await pilot.pause(0.05)
            q1 = world.encoder_q()
            slack = 2 * np.abs(world.nominal.jacobian_q(q1)[0, :3]) @ (one / 2)
            assert np.all(np.abs(world.nominal.position(q1) - world.nominal.position(q0) - [1e-3, 0, 0]) <= slack)
            # a 4-joint arm cannot turn its tool about base X: refused, nothing moves
            await pilot.press("t")
            np.testing.assert_array_equal(world.encoder_q(), q1)
            assert "tool position only" in ctl.message
            await pilot.press("m", "enter")
            assert ctl.session.samples() == [] and "no contact" in ctl.message
            robot.move_joints(q_touch, speed=1.0)  # jogged onto the needle
            for _ in range(100):  # the UI polls every 0.1 s; a loaded machine may take longer
                if "CONTACT" in str(app.query_one("#jog").render()):
                    break
                await pilot.pause(0.02)
            assert world.contact() and "CONTACT" in str(app.query_one("#jog").render())
            await pilot.press("p", "enter")  # label B
            assert [s.point for s in ctl.session.samples()] == ["B"]
            rows = read_samples(ctl.session.samples_csv, world.nominal.joints)
            np.testing.assert_allclose(rows.q[0], world.encoder_q(), atol=one.max())
            # a servo hardware error: banner, motion refused
            world.faults.inject("device_fault", device=13)
            for _ in range(30):
                await pilot.pause(0.05)
                if ctl.fault:
                    break
            assert ctl.fault and app.query_one("#banner").has_class("on")
            held = world.encoder_q()
            await pilot.press("q")
            np.testing.assert_allclose(world.encoder_q(), held, atol=1e-12)

    asyncio.run(run())
    _, events = read_journal(ctl.session.folder / "journal.jsonl")
    kinds = [e["type"] for e in events]
    assert kinds.count("sample") == 1 and "fault" in kinds and kinds[-1] == "end"
