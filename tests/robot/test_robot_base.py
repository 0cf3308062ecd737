"""The robot base (lifecycle, URL options, pre-checks), the capability protocols and the entry-point registry."""

from __future__ import annotations

import re
import subprocess
import sys
import textwrap
from importlib.metadata import EntryPoint
from pathlib import Path

import numpy as np
import pytest
from station.mocks.world import World

from station.robot import (
    CalibrationExport,
    CalibrationStore,
    CartesianMotion,
    Compliant,
    ConfigError,
    ConnectionLost,
    ContactSensor,
    FaultRecovery,
    LimitError,
    Reboot,
    Reconnect,
    Robot,
    SafetyStop,
    UnlockProtectiveStop,
    capabilities_of,
    open_robot,
    parse_url,
    schemes,
)
from station.robot import registry as registry_module
from station.robot.base import RobotBase
from station.robot.url import REQUIRED, Option, Options, either, flag, id_list, integer, number, text

DOCS = Path(__file__).resolve().parents[2] / "docs"


# ---- declarative URL options ---------------------------------------------------------------------------------
SPEC = Options(
    Option("model", text(), REQUIRED, "kinematic model"),
    Option("nodes", id_list(), None, "node ids", default_doc="1-n"),
    Option("sync_ms", number(0.5, 1000, unit="ms"), 4.0, "SYNC period"),
    Option("retries", integer(0, 10), 3, "retries"),
    Option("fast", flag(), True, "fast sync read"),
    Option("contact", either("auto", none=("none",), otherwise=integer(1, 127)), "auto", "contact node"),
)


def test_options_parse_values_and_fill_defaults():
    got = SPEC.parse(parse_url("x://h?model=arm6&nodes=1-3,5&sync_ms=2.5&fast=0&contact=none"))
    assert got == {"model": "arm6", "nodes": [1, 2, 3, 5], "sync_ms": 2.5, "retries": 3, "fast": False,
                   "contact": None}
    assert SPEC.parse(parse_url("x://h?model=m&contact=7"))["contact"] == 7
    assert SPEC.parse(parse_url("x://h?model=m"))["contact"] == "auto"


@pytest.mark.parametrize("query,words", [
    ("model=m&bogus=1&other=2", ["unknown option(s) bogus, other", "known: contact, fast, model"]),
    ("nodes=1-6", ["add model=", "kinematic model"]),
    ("model=m&sync_ms=0.1", ["sync_ms='0.1'", "number in [0.5, 1000] ms"]),
    ("model=m&sync_ms=nan", ["sync_ms='nan'"]),
    ("model=m&retries=2.5", ["retries='2.5'", "integer 0..10"]),
    ("model=m&nodes=6-1", ["nodes='6-1'", "id list"]),
    ("model=m&contact=200", ["contact='200'", "auto / none / integer 1..127"]),
    ("model=m&fast=maybe", ["fast='maybe'", "1 or 0"]),
])
def test_options_refuse_with_one_line_naming_url_and_option(query, words):
    url = f"x://h?{query}"
    with pytest.raises(ConfigError) as e:
        SPEC.parse(parse_url(url))
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"robot URL {url!r}: ")
    for w in words:
        assert w in msg


@pytest.mark.parametrize("driver,page", [("dynamixel", "hardware-dynamixel.md"),
                                         ("canopen+virtual", "hardware-canopen.md"), ("ur", "hardware-ur.md"),
                                         ("franka", "hardware-franka.md")])
def test_hardware_pages_show_the_drivers_option_spec(driver, page):
    """The URL option table in each hardware page is the one the driver declares (``Options.markdown()``)."""
    table = registry_module.driver_class(driver).options.markdown()
    assert table in (DOCS / page).read_text(), f"docs/{page}: paste the table from {driver}'s options:\n{table}"


# ---- lifecycle and pre-checks (a bus-less robot: only the base is under test) ---------------------------------
class PaperRobot(RobotBase):
    """A robot on paper: records what would go on the wire."""

    options = Options(Option("model", text(), "omx", "kinematic model"))

    def __init__(self, model: str = "omx", fail: bool = False) -> None:
        from station.kinematics import load_model

        self.model = load_model(model)
        self.sent: list = []
        self.shutdowns = 0
        if fail:
            self.close()  # as a driver does when its constructor fails half way
            raise ConnectionLost("no answer")

    @classmethod
    def from_url(cls, url, **overrides):
        return cls(cls.options.parse(url)["model"], **overrides)

    def _shutdown(self) -> None:
        self.shutdowns += 1

    def move_joints(self, q, speed=None, wait=True):
        target = self._checked_target(q, "move_joints")
        speed = self._checked_speed(speed, "move_joints")
        self._check_stiff("move_joints")
        self.sent.append((target, speed))


def test_close_runs_shutdown_once_and_context_manager_closes():
    r = PaperRobot()
    with r as same:
        assert same is r and not r.closed
    assert r.closed and r.shutdowns == 1
    r.close()
    r.close()
    assert r.shutdowns == 1
    with pytest.raises(ConnectionLost, match="closed"):
        r.move_joints(np.zeros(4))
    assert r.sent == []
    assert "closed" in repr(r)


def test_half_built_robot_closes_once():
    with pytest.raises(ConnectionLost):
        PaperRobot(fail=True)


def test_shared_motion_prechecks_refuse_before_sending():
    r = PaperRobot()
    mid = (r.model.lower + r.model.upper) / 2
    r.move_joints(mid, speed=0.5)
    bad = mid.copy()
    bad[1] = r.model.upper[1] + 0.01
    with pytest.raises(LimitError, match="joint 2 .* outside its limits"):
        r.move_joints(bad)
    for speed in (0.0, -1.0, float("nan"), float("inf"), "fast"):
        with pytest.raises(LimitError, match="speed"):
            r.move_joints(mid, speed=speed)
    r._compliant = True
    with pytest.raises(SafetyStop, match="compliant"):
        r.move_joints(mid)
    assert len(r.sent) == 1
    with pytest.raises(LimitError, match="outside"):
        r._checked_speed(0.3, "jog", "m/s", 0.25)
    with pytest.raises(LimitError, match="step must be finite"):
        r._jog_target(mid, "joint", 0, float("nan"))


def test_jog_plan_keeps_the_tool_under_the_manual_cap():
    r = PaperRobot()
    q0 = (r.model.lower + r.model.upper) / 2
    target, lead = r._jog_plan(q0, "cartesian", 2, 0.01, None, joint_default=None, tool_default=0.25)
    # independent check: tool speed along the straight joint path at the lead joint's speed
    dq = target - q0
    s = np.linspace(0, 1, 50)[:, None]
    J = r.model.jacobian_q(q0 + s * dq)[:, :3]
    tool = np.linalg.norm(J @ (dq / np.max(np.abs(dq)) * lead), axis=1)
    assert tool.max() <= 0.25 * 1.02 and tool.max() >= 0.25 * 0.5


# ---- capabilities ------------------------------------------------------------------------------------------
def test_capability_matrix_of_the_shipped_drivers():
    """What docs/hardware.md says each driver can do, asked the way the engine asks: ``isinstance``."""
    from station.drivers.canopen import CanopenRobot
    from station.drivers.dynamixel import DynamixelRobot
    from station.drivers.ur import URRobot

    expected = {
        DynamixelRobot: {CalibrationStore, ContactSensor, Compliant, Reboot},
        CanopenRobot: {CalibrationStore, ContactSensor, Compliant},
        URRobot: {CalibrationStore, CalibrationExport, ContactSensor, Compliant, CartesianMotion,
                  UnlockProtectiveStop, Reconnect},
    }
    every = {CalibrationStore, CalibrationExport, ContactSensor, Compliant, CartesianMotion, UnlockProtectiveStop,
             Reboot, Reconnect}
    for cls, caps in expected.items():
        assert {c for c in every if issubclass(cls, c)} == caps, cls.__name__
        assert issubclass(cls, RobotBase)
    assert not issubclass(CanopenRobot, FaultRecovery) and issubclass(DynamixelRobot, FaultRecovery)


def test_a_live_robot_is_a_robot_and_reports_its_capabilities(emulators):
    world = World.default(model="arm6", seed=1)
    with open_robot(emulators("canopen", world).url) as robot:
        assert isinstance(robot, Robot)
        assert capabilities_of(robot) == ["CalibrationStore", "ContactSensor", "Compliant"]
    assert robot.closed
    robot.close()  # again: nothing happens
    with pytest.raises(ConnectionLost, match="closed"):
        robot.move_joints(world.encoder_q())


# ---- registry ----------------------------------------------------------------------------------------------
def test_builtin_drivers_come_from_entry_points():
    assert {"dynamixel", "canopen+virtual", "canopen+socketcand", "ur"} <= set(schemes())
    known = r"known: canopen\+ixxat.*canopen\+socketcand"
    with pytest.raises(ConfigError, match=r"ttyS0'?: unknown scheme 'serial'; " + known):
        open_robot("serial:///dev/ttyS0")


def test_a_new_bus_is_an_entry_point_not_a_core_edit(tmp_path, monkeypatch):
    pkg = tmp_path / "paperbus"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(textwrap.dedent('''
        from station.robot.base import RobotBase
        from station.robot.url import Option, Options, integer

        class PaperBus(RobotBase):
            options = Options(Option("axes", integer(1, 9), 6, "axes"))

            def __init__(self, url, axes):
                self.url, self.axes = url, axes

            @classmethod
            def from_url(cls, url, **overrides):
                return cls(url.raw, **{**cls.options.parse(url), **overrides})

            def _shutdown(self):
                pass
    '''))
    monkeypatch.syspath_prepend(str(tmp_path))
    eps = dict(registry_module.REGISTRY.entries())
    eps["paper"] = EntryPoint(name="paper", value="paperbus:PaperBus", group=registry_module.GROUP)
    monkeypatch.setattr(registry_module.REGISTRY, "_entries", eps)
    robot = open_robot("paper://bench?axes=4")
    assert type(robot).__name__ == "PaperBus" and robot.axes == 4
    with pytest.raises(ConfigError, match="axes='12'"):
        open_robot("paper://bench?axes=12")


BLOCK = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {blocked!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
sys.meta_path.insert(0, Block())
from station.robot import ConfigError, open_robot
try:
    open_robot({url!r})
except ConfigError as e:
    print("ConfigError:", e)
"""


@pytest.mark.parametrize("url,blocked,package", [
    ("ur://127.0.0.9", ["rtde_control"], "ur-rtde"),
    ("canopen+virtual://x?model=arm6", ["canopen"], "canopen"),
    ("canopen+virtual://x?model=arm6", ["can"], "python-can"),
    ("dynamixel:///dev/null?model=omx", ["dynamixel_sdk"], "dynamixel-sdk"),
])
def test_missing_bus_library_is_one_line_naming_the_package(url, blocked, package):
    out = subprocess.run([sys.executable, "-c", BLOCK.format(blocked=blocked, url=url)], capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ConfigError: robot URL"), out.stdout
    assert re.search(rf"pip install {re.escape(package)}$", lines[0]), lines[0]
