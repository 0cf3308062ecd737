"""Shared rig of the fault and durability tests (tests/e2e: test_fault*, test_durability*): a demo cell on an
emulator, the bus's safe state read on the emulator/world side, a fault hooked into a phase of a real session.
One place, so the fault files do not each grow their own copy. The station itself runs through the one CLI
runner (tests/clirunner.py); a station child killed in a phase is ``station_proc(..., prelude=kill_in(phase))``.

Ground truth is always the simulated world or the emulated devices, never the station's own word."""

from __future__ import annotations

import contextlib
import os
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from busrig import CANOPEN_RELAXED
from station.mocks.launch import launch

from station.cli.run_cmd import write_demo_files
from station.engine import read_journal


def samples(journal: Path) -> list:
    return [e for e in read_journal(journal)[1] if e.type == "sample"]


@dataclass
class DemoCell:
    """The demo world (hidden zero offsets) on one bus's emulator, its cell file and a records database."""

    bus: str
    url: str
    world_path: Path
    cell_path: Path
    serial: str
    db: str
    home: Path
    emu: object  # station.mocks.launch.Emulator, or the CanopenEmulator behind a socketcand hub
    world: object | None  # the World the emulator serves (None: UR, in its own process)
    extra: dict = field(default_factory=dict)

    @property
    def env(self) -> dict:
        return {**os.environ, "STATION_HOME": str(self.home)}

    def journal(self) -> Path:
        return next((self.home / "sessions").glob("*/journal.jsonl"))


@contextlib.contextmanager
def demo_cell(bus: str, tmp_path: Path, seed: int, *, cross_process: bool = False, world_doc=None,
              relaxed: bool = False):
    """A demo cell on ``bus``. ``cross_process``: reachable from a station child process too (CANopen through a
    socketcand hub, python-can's real client; Dynamixel on a pty; UR always is). ``world_doc(doc)`` may edit the
    world document before the emulator starts. ``relaxed`` (CANopen drives in this process): the URL carries the
    documented consumer, SDO and master-consumer times relaxed (``busrig.CANOPEN_RELAXED`` says why) for tests
    that are not heartbeat or SDO timing tests."""
    import yaml

    world_path, cell_path, serial = write_demo_files(bus, tmp_path, seed=seed, time_mode="instant")
    if world_doc is not None:
        doc = yaml.safe_load(world_path.read_text())
        world_doc(doc)
        world_path.write_text(yaml.safe_dump(doc))
    home, db = tmp_path / "home", f"sqlite:///{tmp_path / 'records.db'}"
    if bus == "canopen" and cross_process:
        from station.mocks.canopen.emulator import CanopenEmulator
        from station.mocks.canopen.hub import SocketcandHub
        from station.mocks.world import World

        chan = f"d-{uuid.uuid4().hex[:8]}"
        emu = CanopenEmulator(World.from_file(world_path), channel=chan).start()
        # as a socketcand daemon started with -e 0x1FFFFFFF: error frames reach the station (by default socketcand
        # forwards none: tests/drivers/canopen/test_canopen_socketcand.py)
        hub = SocketcandHub(chan, port=0, error_mask=0x1FFFFFFF).start()
        try:
            url = f"canopen+socketcand://127.0.0.1:{hub.port}?channel=can0&nodes=1-6&model=arm6"
            yield DemoCell(bus, url, world_path, cell_path, serial, db, home, emu, emu.world)
        finally:
            hub.stop()
            emu.stop()
        return
    world = None
    if bus != "ur":
        from station.mocks.world import World

        world = World.from_file(world_path)
    with launch(bus, world if world is not None else world_path, serial=serial) as emu:
        if relaxed and bus == "canopen":
            emu.url += CANOPEN_RELAXED
        yield DemoCell(bus, emu.url, world_path, cell_path, serial, db, home, emu, world)


# ---- the bus's safe state, read where the truth is ------------------------------------------------------------
def canopen_states(emu) -> list[str]:
    """CiA 402 state of every emulated drive (``emu``: a CanopenEmulator or a launched one)."""
    from station.drivers.canopen.cia402 import state_of

    drives = getattr(emu, "drives", None) or emu.emulator.drives
    return [state_of(int(d.get(0x6041))) for d in drives.values()]


def ur_truth(emu, timeout: float = 3.0) -> tuple[str, str, list[float]]:
    """(program state, safety mode, encoder angles) from the UR emulator's dashboard (retried while the
    controller drops its connections)."""
    end = time.monotonic() + timeout
    while True:
        try:
            enc = [float(x) for x in emu.dashboard("emulator encoder").split()[1:]]
            return emu.dashboard("programstate"), emu.dashboard("safetymode"), enc
        except OSError:
            if time.monotonic() > end:
                raise
            time.sleep(0.1)


def assert_safe(cell: DemoCell, *, settle: float = 0.3, kill_9: bool = False, loud: list[str] = ()) -> str:
    """The bus is in its safe state: nothing moves, the arm is not left compliant, and per bus: Dynamixel servos
    hold their position (torque stays on by design: an arm must not drop), CiA 402 drives are not in OPERATION
    ENABLED (power stage off, brakes hold), the UR program is stopped. After ``kill_9`` (no teardown ran) only
    that nothing moves: the devices' own reaction (the move ends, heartbeat/watchdog). A Dynamixel arm left
    compliant is accepted only when the teardown said so in ``loud`` (the station's warnings): one line "could
    not leave the bus safe" naming the servos (a pulled cable cannot be talked through). Returns a description."""
    time.sleep(settle)
    if cell.bus == "ur":
        state, safety, q0 = ur_truth(cell.emu)
        time.sleep(0.1)
        q1 = ur_truth(cell.emu)[2]
        assert max(abs(a - b) for a, b in zip(q0, q1, strict=True)) < 1e-9, "the UR arm still moves"
        if not kill_9:
            assert not state.startswith("PLAYING"), state
        return f"{state.split()[0]}, {safety.split()[-1]}"
    world = cell.world
    assert not world.is_moving(), "the arm still moves"
    if kill_9:
        return "not moving" + (", compliant (the next run resets it)" if world.compliant else "")
    if world.compliant and cell.bus == "dynamixel":
        said = [x for x in loud if "could not leave the bus safe" in x and "COMPLIANT" in x and "\n" not in x]
        assert len(said) == 1, f"the arm was left compliant and the teardown did not say so once: {loud}"
        ids = cell.emu.emulator.joint_ids
        assert str(list(ids)) in said[0], said[0]
        return "not moving, compliant: said loudly (the next run resets it)"
    assert not world.compliant, "the arm was left compliant"
    if cell.bus == "canopen":
        states = canopen_states(cell.emu)
        assert "OPERATION ENABLED" not in states, states
        return ", ".join(sorted(set(states)))
    return "stopped, holding"


# ---- the calibration the devices hold, read on the emulator side -------------------------------------------
def device_offsets(cell: DemoCell) -> list:
    """Per joint, the raw zero offset the emulated devices hold: Dynamixel Homing Offset (20) ticks; CANopen
    (the zero a homing applied, 0x6064 - 0x6063, and the value stored by 0x1010) counts, so an offset that would
    not survive a power cycle shows."""
    from station.mocks.canopen.eds import POSITION_OFFSET

    if cell.bus == "dynamixel":
        emu = cell.emu.emulator
        return [int(emu.devices[i].get("homing_offset")) for i in emu.joint_ids]
    drives = getattr(cell.emu, "drives", None) or cell.emu.emulator.drives
    out = []
    for d in drives.values():
        stored = d.stored.get((POSITION_OFFSET, 0))  # never stored: the default, 0, is what a power cycle brings
        out.append((d.position_offset, 0 if stored is None else int.from_bytes(stored[:4], "little", signed=True)))
    return out


def counts_of(cell: DemoCell, offsets: dict[str, float]) -> list:
    """``{"offset.jN": rad}`` in the devices' raw units (the model's encoder), shaped as :func:`device_offsets`."""
    out = []
    for j, joint in enumerate(cell.world.nominal.joints):
        enc = joint.encoder
        c = int(round(offsets[f"offset.j{j + 1}"] * enc.counts_per_unit * enc.gear * enc.direction))
        out.append(c if cell.bus == "dynamixel" else (c, c))
    return out


# ---- a fault in a phase of a real session ------------------------------------------------------------------
# the engine call each phase of the checklist starts with (procedures/zero_offsets.py), and which call of it
PHASE_CALLS = {"motion": ("approach", 3), "record": ("record", 3), "solve": ("solve", 1),
               "write-back": ("write_back", 1)}


def phase_hook(phase: str, act, *, in_write: bool = False):
    """``(name, method)``: a replacement for ``Session.<name>`` that runs ``act(session)`` as the phase starts (the
    3rd approach, the 3rd record, the solve, the write-back); with ``in_write`` inside the write-back's device
    write (the window whose signals are held). Install it with monkeypatch in-process, or in a station child
    process through its prelude, :func:`kill_in`."""
    from station.engine.session import Session

    name, nth = PHASE_CALLS[phase]
    orig = getattr(Session, name)
    calls = {"n": 0}

    def hooked(self, *a, **kw):
        calls["n"] += 1
        if calls["n"] == nth:
            if in_write:  # the device write, or a UR's export (its controller keeps its own calibration)
                robot, done = self.robot, []
                for attr in ("write_calibration", "export_calibration"):
                    if hasattr(robot, attr):
                        def act_then(*a, _real=getattr(robot, attr), **k):
                            if not done:
                                done.append(True)
                                act(self)
                            return _real(*a, **k)

                        setattr(robot, attr, act_then)
            else:
                act(self)
        return orig(self, *a, **kw)

    return name, hooked


def kill_in(phase: str) -> str:
    """The ``prelude`` (tests/clirunner.py) of a station child that kills itself with SIGKILL as ``phase`` starts
    (inside the device write for write-back): no teardown runs, as when the power or the process is lost."""
    return f"""
import os, signal, sys
sys.path.insert(0, {str(Path(__file__).parent)!r})
from faultrig import phase_hook
from station.engine.session import Session
setattr(Session, *phase_hook({phase!r}, lambda s: os.kill(os.getpid(), signal.SIGKILL),
                             in_write={phase == "write-back"}))
"""


def realtime_ur(tmp_path: Path, emulators, seed: int):
    """A UR5e emulator process on a real-time world (faults and hangs are timed on the wall clock)."""
    import yaml
    from station.mocks.world import default_doc

    doc = default_doc("ur5e", seed=seed)
    doc["motion"].update(time_mode="realtime")
    path = tmp_path / "w.yaml"
    path.write_text(yaml.safe_dump(doc))
    return emulators("ur", path)
