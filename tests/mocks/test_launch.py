"""The one emulator launcher (``station.mocks.launch``): the URL it hands out opens the robot the world file
describes, on every bus and in both process modes; children never outlive their parent."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import yaml
from clirunner import python_spawn, station_proc
from station.mocks.errors import MockError
from station.mocks.launch import launch
from station.mocks.world import World

from station.robot import open_robot


def _world_file(tmp_path: Path, model: str, buses: dict) -> Path:
    world = World.default(model=model, seed=4, buses=buses)
    path = tmp_path / f"{model}.yaml"
    path.write_text(yaml.safe_dump(world.to_dict()))
    return path


@pytest.mark.parametrize("process", [False, True])
def test_dynamixel_url_follows_the_world_files_bus_settings(tmp_path, emulators, process):
    path = _world_file(tmp_path, "omx", {"dynamixel": {"ids": "21-24", "contact_id": 201}})
    emu = emulators("dynamixel", path, serial="OMX 7/1", process=process)
    assert emu.url.startswith(f"dynamixel://{emu.port}?") and "serial=OMX%207%2F1" in emu.url
    with open_robot(emu.url + "&latency=50") as robot:
        ident = robot.identity()
        assert [d["id"] for d in ident.devices] == [21, 22, 23, 24, 201]  # servos and the contact sensor
        assert ident.serial == "OMX 7/1" and robot.touch() is False
        truth = World.from_file(path).encoder_q()
        tick = 1 / robot.model.joints[0].encoder.counts_per_unit
        assert abs(robot.joint_positions().q - truth).max() <= tick / 2 + 1e-12


def test_canopen_in_process_serves_the_world_object(emulators):
    world = World.default(model="arm6", seed=2, buses={"canopen": {"nodes": [3, 4, 5, 6, 7, 8]}})
    emu = emulators("canopen", world, serial="A6-9")
    assert emu.world is world and "nodes=3,4,5,6,7,8" in emu.url
    with open_robot(emu.url) as robot:
        assert [d["node"] for d in robot.identity().devices] == [3, 4, 5, 6, 7, 8]
        assert robot.identity().serial == "A6-9"


def test_ur_child_on_a_random_loopback_address(tmp_path, emulators):
    path = _world_file(tmp_path, "ur5e", {"ur": {"serial": "20235512345"}})
    a, b = emulators("ur", path), emulators("ur", path)
    assert a.host != b.host and a.host.startswith("127.") and a.url == f"ur://{a.host}?model=ur5e&power_on=yes"
    assert a.dashboard("get serial number") == "20235512345"


def test_bad_requests_are_refused():
    with pytest.raises(MockError, match="no emulator for bus 'profibus'"):
        launch("profibus")
    with pytest.raises(ValueError, match="child process only"):
        launch("ur", process=False)


def test_a_child_ends_with_its_parent(tmp_path):
    """A test process killed with -9 leaves no emulator behind (``--exit-with-parent``)."""
    path = _world_file(tmp_path, "omx", {})
    code = ("import sys, time; from station.mocks.launch import launch\n"
            f"emu = launch('dynamixel', {str(path)!r}, process=True).start()\n"
            "print(emu.proc.pid, flush=True); time.sleep(60)")
    with python_spawn(code) as parent:
        child = int(parent.readline())
        parent.kill()
        parent.wait(10)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and _alive(child):
            time.sleep(0.1)
        assert not _alive(child)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except FileNotFoundError:
        return False


def test_station_demo_with_an_unknown_bus_is_one_line():
    p = station_proc("demo", "--robot", "profibus", timeout=60)
    assert p.code == 2
    from station.mocks.plug import demo_buses

    assert p.err_lines == [f"station: error: --robot must be one of {', '.join(demo_buses())}, "
                                             "got 'profibus'"]


# ---- the emulators' base and registry (station.mocks.emulator, station.mocks.plug) ----------------------------
def test_emulator_base_lifecycle_start_returns_it_stop_is_idempotent_failed_start_releases():
    from station.mocks.emulator import EmulatorBase

    class Paper(EmulatorBase):
        def __init__(self, fail: bool = False) -> None:
            self.fail, self.log = fail, []

        @property
        def url(self) -> str:
            return "paper://bench"

        def _startup(self) -> None:
            self.log.append("up")
            if self.fail:
                raise OSError("port busy")

        def _shutdown(self) -> None:
            self.log.append("down")

    emu = Paper()
    assert emu.start() is emu and emu.start() is emu and emu.started
    emu.stop()
    emu.stop()
    emu.close()
    assert emu.log == ["up", "down"] and not emu.started
    with Paper() as e2:
        assert e2.started and e2.url == "paper://bench"
    assert e2.log == ["up", "down"]
    bad = Paper(fail=True)
    with pytest.raises(OSError, match="port busy"):
        bad.start()
    assert bad.log == ["up", "down"] and not bad.started  # what was opened is released; stop() does nothing more
    bad.stop()
    assert bad.log == ["up", "down"]
    with pytest.raises(NotImplementedError, match="no power cycle"):
        Paper().power_cycle()


def test_a_new_emulator_is_an_entry_point_found_by_launch_mock_and_demo(tmp_path, monkeypatch):
    """A plug of another package, registered only through the ``station.emulators`` entry points: the launcher
    starts it, ``station mock`` lists its command, ``station demo`` offers it."""
    import textwrap
    from importlib.metadata import EntryPoint

    import typer
    from station.mocks import plug as plug_module

    pkg = tmp_path / "papermock"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(textwrap.dedent('''
        import typer
        from station.mocks.emulator import EmulatorBase
        from station.mocks.plug import Demo, Plug

        class PaperEmulator(EmulatorBase):
            def __init__(self, world):
                self.world = world

            @property
            def url(self):
                return "paper://bench?model=arm6"

            def _startup(self):
                pass

            def _shutdown(self):
                pass

        class PaperPlug(Plug):
            bus = "paper"
            cli = "papermock"
            default_model = "arm6"
            demo = Demo(model="arm6")

            def build(self, world):
                return PaperEmulator(world)

        def register(mock_app):
            @mock_app.command("paper", help="Emulated paper bus.")
            def paper():
                pass

        PLUG = PaperPlug()
    '''))
    monkeypatch.syspath_prepend(str(tmp_path))
    eps = {**plug_module.REGISTRY.entries(),
           "paper": EntryPoint(name="paper", value="papermock:PLUG", group=plug_module.GROUP)}
    monkeypatch.setattr(plug_module.REGISTRY, "_entries", eps)
    monkeypatch.setattr(plug_module, "_PLUGS", None)
    with launch("paper", serial="P-1") as emu:
        assert emu.url == "paper://bench?model=arm6&serial=P-1" and emu.world.nominal.name == "arm6"
    assert "paper" in plug_module.demo_buses()
    app = typer.Typer()
    from station.cli import mock_cmd

    monkeypatch.setattr(mock_cmd, "mock_app", typer.Typer())
    mock_cmd.register(app)
    assert "paper" in {c.name for c in mock_cmd.mock_app.registered_commands}
    bad = {**eps, "broken": EntryPoint(name="broken", value="papermock:NOPE", group=plug_module.GROUP)}
    monkeypatch.setattr(plug_module.REGISTRY, "_entries", bad)
    monkeypatch.setattr(plug_module, "_PLUGS", None)
    with pytest.raises(MockError, match="broken"):
        plug_module.plugs()
    monkeypatch.setattr(plug_module, "_PLUGS", None)
