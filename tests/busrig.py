"""Bus rigs: one emulated robot per bus, as the bus-conformance suite (tests/e2e/test_bus_conformance.py) and the load
soak (tests/e2e/test_soak_buses.py) use it. A rig is the demo world of its bus (hidden zero offsets, the cell of
sockets) served by the bus's emulator (``station.mocks.launch``, the ``station.emulators`` plugs), the URL the
station opens, and what the test needs to know about the bus that the station must not be asked: the truth
(joint positions and motion read on the emulator's side of the wire), how to stage a device fault, what a power
cycle must have lost, the documented time in which the arm stops once the station is gone.

A new bus gets the whole suite with one more builder here::

    @rig("mybus")
    def mybus(tmp_path, *, realtime, seed): ... yield Rig(...)

Ground truth is always the emulator's side (the simulated world, the controller's own dashboard, an independent
pylibfranka client), never the driver under test."""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from station.mocks.launch import launch
from station.mocks.plug import find

from station.cli.run_cmd import write_demo_files


# ---- the truth: read on the emulator's side of the wire ------------------------------------------------------
class WorldTruth:
    """An emulator in this process: the World it serves."""

    def __init__(self, world) -> None:
        self.world = world

    def q(self) -> np.ndarray:
        return np.asarray(self.world.encoder_q(), float)

    def moving(self) -> bool:
        return bool(self.world.is_moving())


class URTruth:
    """A UR controller in its own process: its dashboard's emulator commands (the encoders it drives)."""

    def __init__(self, emu) -> None:
        self.emu = emu

    def q(self, timeout: float = 5.0) -> np.ndarray:
        end = time.monotonic() + timeout
        while True:  # retried while the controller reboots or drops its connections
            try:
                return np.array([float(x) for x in self.emu.dashboard("emulator encoder").split()[1:]])
            except (OSError, ValueError):
                if time.monotonic() > end:
                    raise
                time.sleep(0.05)

    def moving(self) -> bool:
        q0 = self.q()
        time.sleep(0.03)  # 15 controller cycles
        return float(np.max(np.abs(self.q() - q0))) > 1e-9


FRANKA_READ = """
import json, sys
import pylibfranka as pf
r = pf.Robot(sys.argv[1], pf.RealtimeConfig.kIgnore)
s = r.read_once()
print(json.dumps({"q": list(s.q), "dq": list(s.dq)}))
"""


class FrankaTruth:
    """franka-sim in its own process: a second, independent FCI client (pylibfranka, not the driver), in a process
    of its own so that a robot that keeps it waiting cannot hang the test. The FCI serves one client: read only
    while the station is not connected."""

    def __init__(self, emu) -> None:
        self.emu = emu

    def state(self) -> dict:
        p = subprocess.run([sys.executable, "-c", FRANKA_READ, self.emu.host], capture_output=True, text=True,
                           timeout=30)
        assert p.returncode == 0, p.stderr[-2000:]
        return json.loads(p.stdout)

    def q(self) -> np.ndarray:
        return np.array(self.state()["q"])

    def moving(self) -> bool:
        return float(np.max(np.abs(self.state()["dq"]))) > 1e-3


# ---- a rig ------------------------------------------------------------------------------------------------------
@dataclass
class Rig:
    name: str  # the test id: bus and wire
    bus: str  # the emulator's plug (station.emulators)
    emu: object  # an EmulatorBase: url, world, power_cycle()
    url: str  # what the station opens
    serial: str
    world_path: Path
    cell_path: Path
    truth: object  # q() -> (n,), moving() -> bool
    tol: np.ndarray  # per joint: a reading's resolution against the truth (SI)
    reach: np.ndarray  # per joint: how close a finished move lands on its target (SI)
    store: bool  # the device keeps the zero offsets (CalibrationStore); else the controller keeps its own (export)
    fault: Callable | None  # stage a device fault now -> the typed errors the station may raise for it
    volatile: Callable  # () -> asserts on the emulator's side what a power cycle must have lost
    cross_process: bool  # a station in another process can open ``url``
    kill_url: str = ""  # the URL a station that is killed mid-move opens (its consumer/watchdog settings)
    kill_bound: float = 0.0  # s: the documented time in which the arm stops once the station is gone
    options: dict = field(default_factory=dict)  # zero_offsets options for this demo world
    truth_while_connected: bool = True  # False: the truth can be read only while no station is connected
    speed: float = 0.2  # rad/s: a slow move (stop and kill tests)

    @property
    def default_url(self) -> str:
        """``url`` with the drivers' default fault thresholds (no relaxed timeouts)."""
        return self.url.replace(CANOPEN_RELAXED, "")

    @property
    def world(self):
        return getattr(self.emu, "world", None)

    def wait_still(self, timeout: float = 5.0) -> float:
        """Wait until the arm stands (truth); the time it took."""
        t0 = time.monotonic()
        while self.truth.moving():
            assert time.monotonic() - t0 < timeout, f"{self.name}: the arm still moves after {timeout} s"
            time.sleep(0.01)
        return time.monotonic() - t0


RIGS: dict[str, Callable[..., contextlib.AbstractContextManager[Rig]]] = {}


def rig(name: str):
    """Register a rig builder ``builder(tmp_path, *, realtime: bool, seed: int) -> iterator of Rig``."""
    def deco(fn):
        RIGS[name] = contextlib.contextmanager(fn)
        return fn
    return deco


def open_rig(name: str, tmp_path: Path, *, realtime: bool = False, seed: int = 21):
    """The rig ``name`` (a context manager): emulator started, stopped at exit."""
    return RIGS[name](tmp_path, realtime=realtime, seed=seed)


def _demo(bus: str, tmp_path: Path, seed: int, time_mode: str):
    return write_demo_files(bus, tmp_path / bus, seed=seed, time_mode=time_mode)


def _quantum(model) -> np.ndarray:
    """Half an encoder count per joint, SI."""
    return np.array([0.5 / (j.encoder.counts_per_unit * j.encoder.gear) for j in model.joints]) + 1e-12


def _options(bus: str) -> dict:
    demo = find(bus).demo
    return dict(demo.options) if demo else {}


# the drives run in the test's own process: at load ~9 on 2 cores their threads wait for the GIL behind the
# station's (2 s gaps measured); these rigs are not heartbeat or SDO timing tests (the kill test and the soak
# are), so the station's consumer, SDO and master-consumer times are the documented URL options, relaxed
CANOPEN_RELAXED = "&heartbeat_timeout_ms=5000&sdo_timeout_ms=2000&master_timeout_ms=5000"


def _canopen_fault(world):
    def fault():
        from station.robot import BusError, DeviceFault, SafetyStop

        world.faults.inject("device_fault", device=3)  # drive 3: EMCY, FAULT
        return (DeviceFault, SafetyStop, BusError)
    return fault


def _canopen_volatile(emu):
    def volatile() -> None:
        # the station's runtime settings are gone (its heartbeat producer time 0x1017 back to the power-up 0,
        # its consumer entries 0x1016 empty) and the power stage is off: SWITCH ON DISABLED
        drives = emu.drives.values()
        assert all(d.get(0x1017) == 0 and not d.consumers() for d in drives), [d.get(0x1017) for d in drives]
        assert {d.state for d in drives} == {"SWITCH ON DISABLED"}, [d.state for d in drives]
    return volatile


@rig("canopen-socketcand")
def canopen_socketcand(tmp_path: Path, *, realtime: bool, seed: int) -> Iterator[Rig]:
    """The same drives behind a socketcand hub: python-can's real socketcand client, reachable from a station in
    another process (the kill test)."""
    from station.mocks.canopen.hub import SocketcandHub
    from station.mocks.plug import find as plug
    from station.mocks.world import World

    world_path, cell_path, serial = _demo("canopen", tmp_path, seed, "realtime" if realtime else "instant")
    world = World.from_file(world_path)
    emu = plug("canopen").build(world)  # on a virtual channel of its own, served by the hub
    with emu, SocketcandHub(emu.channel, port=0) as hub:
        url = f"canopen+socketcand://127.0.0.1:{hub.port}?channel=can0&nodes=1-6&model=arm6&serial={serial}"
        q = _quantum(world.nominal)
        # the killed station's drives watch its heartbeat for 400 ms (master_timeout_ms); its own SDO answers are
        # not what is timed there
        yield Rig("canopen-socketcand", "canopen", emu, url + CANOPEN_RELAXED, serial, world_path, cell_path,
                  WorldTruth(world), q, 2 * q, True, _canopen_fault(world), _canopen_volatile(emu), True,
                  kill_url=url + "&master_timeout_ms=400&sdo_timeout_ms=2000", kill_bound=0.4,
                  options=_options("canopen"))


@rig("canopen-process")
def canopen_process(tmp_path: Path, *, realtime: bool, seed: int) -> Iterator[Rig]:
    """The drives as ``station mock canopen`` in a child process behind its socketcand hub (an interpreter of
    their own, as real drives are not starved by the station's host): the load soak. No truth, fault or
    volatile checks (the conformance suite uses ``canopen-socketcand``)."""
    world_path, cell_path, serial = _demo("canopen", tmp_path, seed, "realtime" if realtime else "instant")
    with launch("canopen", world_path, serial=serial, process=True) as emu:
        yield Rig("canopen-process", "canopen", emu, emu.url, serial, world_path, cell_path, None, np.zeros(0),
                  np.zeros(0), True, None, lambda: None, True, options=_options("canopen"))


@rig("dynamixel")
def dynamixel(tmp_path: Path, *, realtime: bool, seed: int) -> Iterator[Rig]:
    from station.mocks.world import World

    world_path, cell_path, serial = _demo("dynamixel", tmp_path, seed, "realtime" if realtime else "instant")
    world = World.from_file(world_path)
    with launch("dynamixel", world, serial=serial) as emu:
        half = np.array([np.pi / 4096] * world.nominal.n_joints) + 1e-12  # XM430: 4096 ticks a turn

        def fault():
            from station.robot import ConnectionLost, DeviceFault

            world.faults.inject("device_fault", device=emu.emulator.joint_ids[1])  # overload: its torque off
            return (DeviceFault, ConnectionLost)

        def volatile() -> None:
            # RAM to its defaults: torque off, no bus watchdog (the homing offset is EEPROM)
            devs = [emu.emulator.devices[i] for i in emu.emulator.joint_ids]
            assert all(d.get("torque_enable") == 0 and d.get("bus_watchdog") == 0 for d in devs)

        # the Bus Watchdog (98) the driver arms for a waited move: 4 x 20 ms units (docs/hardware-dynamixel.md)
        yield Rig("dynamixel", "dynamixel", emu, emu.url, serial, world_path, cell_path, WorldTruth(world), half,
                  half, True, fault, volatile, True, kill_url=emu.url, kill_bound=_dxl_watchdog(),
                  options=_options("dynamixel"))


@rig("dynamixel-process")
def dynamixel_process(tmp_path: Path, *, realtime: bool, seed: int) -> Iterator[Rig]:
    """The servos as ``station mock dynamixel`` in a child process (its own interpreter, as a real bus's servos
    are not starved by the station's host): the load soak. Its world is read back through no side channel, so
    this rig has no truth, fault or volatile checks (the conformance suite uses ``dynamixel``)."""
    world_path, cell_path, serial = _demo("dynamixel", tmp_path, seed, "realtime" if realtime else "instant")
    with launch("dynamixel", world_path, serial=serial, process=True) as emu:
        yield Rig("dynamixel-process", "dynamixel", emu, emu.url, serial, world_path, cell_path, None,
                  np.zeros(0), np.zeros(0), True, None, lambda: None, True, options=_options("dynamixel"))


def _dxl_watchdog() -> float:
    from station.drivers.dynamixel import table as T

    return T.WATCHDOG_UNITS * 0.020  # Bus Watchdog (98) in 20 ms units


@rig("ur")
def ur(tmp_path: Path, *, realtime: bool, seed: int) -> Iterator[Rig]:
    # instant: the controller's 2 ms cycle is the world's clock, ticked as fast as the controller runs (a
    # procedure's moves take less than their real time); realtime: on the wall clock
    world_path, cell_path, serial = _demo("ur", tmp_path, seed, "realtime" if realtime else "instant")
    with launch("ur", world_path, serial=serial) as emu:
        def fault():
            from station.robot import SafetyStop

            emu.dashboard("emulator protective_stop")
            return (SafetyStop,)

        def volatile() -> None:
            # the controller boots with the arm powered off, no program running
            assert emu.dashboard("robotmode") == "Robotmode: POWER_OFF"
            assert emu.dashboard("programstate").startswith("STOPPED")

        exact = np.full(6, 1e-9)  # RTDE sends the encoders' doubles
        yield Rig("ur", "ur", emu, emu.url, serial, world_path, cell_path, URTruth(emu), exact, exact, False,
                  fault, volatile, True, kill_url=emu.url, kill_bound=_ur_watchdog(), options=_options("ur"))


def _ur_watchdog() -> float:
    return 0.5  # the RTDE watchdog of a waited move (docs/hardware-ur.md)


@rig("franka")
def franka(tmp_path: Path, *, realtime: bool, seed: int) -> Iterator[Rig]:
    world_path, cell_path, serial = _demo("franka", tmp_path, seed, "realtime")
    with launch("franka", world_path, serial=serial) as emu:
        def volatile() -> None:
            # motions are gone; franka-sim has no brakes: the arm is back at the world's start pose, standing
            from station.mocks.world import World

            state = FrankaTruth(emu).state()
            start = World.from_file(world_path).encoder_q()
            assert np.max(np.abs(np.array(state["q"]) - start)) < 1e-3 and np.max(np.abs(state["dq"])) < 1e-3

        # the physics reports what libfranka reads (float64 from the simulator); a move lands within the async
        # generator's tolerance. retries=8: this host runs test workers beside the simulator's 1 kHz loop and
        # the driver's own (compliance, the seating press); the violations that came in runs here were the
        # test worker's garbage collections (fixed: drivers/franka/stream.py), the margin stays for the load;
        # recovering and retrying is the driver's documented answer (docs/hardware-franka.md, URL options)
        def fault():
            # a person bumps into the arm: a push on the tool staged in the simulator (SIGUSR1, simhost.py), which
            # the collision reflex answers during a motion (the thresholds the driver set)
            import os
            import signal

            from station.robot import SafetyStop

            os.kill(emu.proc.pid, signal.SIGUSR1)
            return (SafetyStop,)

        url = emu.url + find("franka").demo.query + "&retries=8"
        yield Rig("franka", "franka", emu, url, serial, world_path, cell_path,
                  FrankaTruth(emu), np.full(7, 1e-9), np.full(7, 5e-3), False, fault, volatile, True,
                  kill_url=emu.url, kill_bound=0.5, options=_options("franka"), truth_while_connected=False,
                  speed=0.3)
