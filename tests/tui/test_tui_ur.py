"""The jog UI on the third bus: the UR emulator process through the real ur_rtde client. The world lives in the
emulator process, so positions are checked on the driver's readout (which tests/drivers/ur/test_ur_driver.py checks
against the world's truth)."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from station.mocks.world import default_doc

from station.engine.journal import read_journal
from station.robot import open_robot
from station.tui.app import JogApp
from station.tui.controller import JogController
from station.tui.session import session_header, technician_session

START = [0.1, -1.45, 1.6, -1.72, -1.5708, 0.2]


pytestmark = pytest.mark.usefixtures("tui_no_idle_wait")  # see tests/conftest.py


@pytest.fixture
def ur(tmp_path, emulators):
    doc = default_doc("ur5e", seed=3)
    doc["motion"].update(time_mode="sim", start=list(START))  # the controller's 2 ms cycle drives the world
    doc["buses"] = {"ur": {"serial": "20235500001"}}
    path = tmp_path / "world.yaml"
    path.write_text(yaml.safe_dump(doc))
    robot = open_robot(emulators("ur", path).url)
    try:
        yield robot
    finally:
        robot.close()


def jog_controller(robot, folder, serial: str = "20235500001") -> JogController:
    header = session_header(identity=robot.identity(), model_name="ur5e", serial=serial,
                            identify="offsets", reference="unknown", url="ur://")
    return JogController(robot, technician_session(robot, header, folder=folder), identify="offsets")


async def wait_still(pilot, ctl, timeout=10.0):
    end = time.monotonic() + timeout
    await pilot.pause(0.1)
    while time.monotonic() < end:
        r = ctl.poll(block=True)
        if r is not None and not r.moving:
            return r
        await pilot.pause(0.05)
    raise AssertionError("still moving")


@pytest.mark.timeout(120)
def test_jog_and_record_on_ur(ur, tmp_path):
    robot = ur
    robot.enable()
    ctl = jog_controller(robot, tmp_path / "s")
    model = robot.model

    async def run():
        app = JogApp(ctl, poll_s=0.2)
        async with app.run_test(size=(150, 50)) as pilot:
            q0 = (await wait_still(pilot, ctl)).q
            await pilot.press("3", "q")  # J1 +1 deg
            q1 = (await wait_still(pilot, ctl)).q
            assert q1[0] - q0[0] == pytest.approx(np.deg2rad(1.0), abs=2e-4)
            assert np.max(np.abs(q1[1:] - q0[1:])) < 2e-4
            p0 = model.position(q1)
            await pilot.press("m", "2", "e")  # Cartesian Z +0.1 mm
            q2 = (await wait_still(pilot, ctl)).q
            np.testing.assert_allclose(model.position(q2) - p0, [0, 0, 1e-4], atol=3e-5)
            await pilot.press("exclamation_mark")  # no contact here: record anyway, marked forced
            assert len(ctl.session.samples()) == 1

    asyncio.run(run())
    _, events = read_journal(tmp_path / "s" / "journal.jsonl")
    samples = [e for e in events if e["type"] == "sample"]
    assert len(samples) == 1 and samples[0]["status"]["forced"] is True and samples[0]["raw_unit"] == "rad"


@pytest.mark.exclusive  # the dialog waits on a live UR emulator: run alone (make test)
@pytest.mark.timeout(120)
def test_ur_writeback_is_an_honest_export(ur, tmp_path):
    """The UR path is an export. The dialog says so, the controller is unchanged, the journal,
    the record and the report say "exported to PATH, controller unchanged", no after values, no restore."""
    from station.engine.session_record import session_from_journal
    from station.report.render import write_report
    from station.tui.app import ConfirmScreen, WritebackScreen

    robot = ur
    robot.enable()
    ctl = jog_controller(robot, tmp_path / "s")
    assert ctl.ur_rotvec
    rng = np.random.default_rng(3)
    for _ in range(8):  # forced records at spread poses: enough for a solve to export
        robot.move_joints(np.array(START) + rng.uniform(-0.2, 0.2, 6), speed=1.0)
        assert ctl.record(force=True) is not None, ctl.message
    assert ctl.solve_state.result is not None, ctl.solve_state.message
    cal_before = robot.read_calibration()

    async def run():
        app = JogApp(ctl, poll_s=0.2)
        async with app.run_test(size=(150, 50)) as pilot:
            assert "rotation vector" in app.query_one("#tcp").border_title
            q_before = (await wait_still(pilot, ctl)).q
            await pilot.press("W")
            end = time.monotonic() + 10  # a loaded machine may take a while to show the dialog
            while not isinstance(app.screen, ConfirmScreen) and time.monotonic() < end:
                await pilot.pause(0.05)
            screen = app.screen
            assert isinstance(screen, ConfirmScreen) and not isinstance(screen, WritebackScreen)
            text = screen.question  # what the dialog shows (#cf-question)
            assert "unchanged" in text and str(tmp_path / "s" / "controller-calibration") in text
            assert "after" not in text.lower()  # no invented before/after values
            await pilot.press("y")
            end = time.monotonic() + 10
            while not ctl.exported and time.monotonic() < end:
                await pilot.pause(0.05)
            assert ctl.message == f"exported to {tmp_path / 's' / 'controller-calibration'}, controller unchanged"
            q_after = (await wait_still(pilot, ctl)).q
            np.testing.assert_allclose(q_after, q_before, atol=1e-6)  # nothing moved, nothing written
            assert not ctl.writeback_failed  # so W never offers a restore
            await pilot.press("W")
            await pilot.pause(0.2)
            assert not isinstance(app.screen, WritebackScreen)  # an export again at most, never a restore
            await pilot.press("n")

    asyncio.run(run())
    assert robot.read_calibration() == cal_before
    files = ctl.exported
    assert files and all(Path(f).exists() and Path(f).parent == tmp_path / "s" / "controller-calibration"
                         for f in files)
    assert any(f.endswith("calibration.conf") for f in files)
    ctl.close()
    _, events = read_journal(tmp_path / "s" / "journal.jsonl")
    wbs = [e for e in events if e["type"] == "writeback"]
    assert [w["phase"] for w in wbs] == ["exported"] and not wbs[0]["applied"]
    assert wbs[0]["after"] is None and "controller unchanged" in wbs[0]["note"]
    rec = session_from_journal(tmp_path / "s")
    assert rec["writeback"]["phase"] == "exported" and rec["writeback"]["after"] is None
    html = write_report(rec, tmp_path / "report").read_text()
    assert "controller unchanged" in html and "controller-calibration" in html


@pytest.mark.timeout(120)
def test_hold_to_run_on_ur_uses_the_velocity_jog(ur, tmp_path):
    """On a UR, hold-to-run re-sends a speedJ each tick (ur_rtde's moveJ would re-plan on every new target:
    measured 8 of 25 mm/s, standstill 0.5 s late); the key's repeats stopping stops the arm."""
    robot = ur
    robot.enable()
    ctl = jog_controller(robot, tmp_path / "s")
    try:
        ctl.set_continuous()
        assert ctl.continuous, ctl.message
        q0 = robot.joint_positions().q
        start = time.monotonic()
        while time.monotonic() - start < 0.5:  # joint 0 held (+) for 0.5 s, repeats every 35 ms
            now = time.monotonic()
            assert ctl.hold(0, +1, now), (ctl.message, ctl.fault)
            ctl.hold_tick(now)
            time.sleep(0.035)
        assert ctl.last_jog["hold"] and ctl.last_jog["velocity"] > 0
        while ctl.hold_state is not None:
            time.sleep(0.01)
            ctl.hold_tick()
        assert "released" in ctl.message
        end = time.monotonic() + 2.0
        while robot.status().moving:
            assert time.monotonic() < end
            time.sleep(0.005)
        dq = robot.joint_positions().q - q0
        assert dq[0] > 0.005 and np.all(np.abs(dq[1:]) < 1e-9), dq
    finally:
        ctl.close()
