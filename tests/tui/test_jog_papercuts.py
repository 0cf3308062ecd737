"""Papercuts: the example world's bus sections fit the robot it describes, and the README's jog
command survives a POSIX shell."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
from station.mocks.canopen.emulator import CanopenEmulator
from station.mocks.world import World
from station.mocks.world.example import example_text

from station.kinematics import builtin_names, load_model

README = Path(__file__).resolve().parents[2] / "README.md"


def _with_encoders(name: str) -> bool:
    return all(j.encoder is not None for j in load_model(name).joints)


@pytest.mark.parametrize("name", [n for n in builtin_names() if load_model(n).n_joints != 6 and _with_encoders(n)]
                         + ["arm6"])
def test_example_world_has_one_device_per_joint(tmp_path, name):
    f = tmp_path / "world.yaml"
    f.write_text(example_text(name))
    world = World.from_file(f)
    n = load_model(name).n_joints
    assert len(world.bus_config("canopen")["nodes"]) == n
    assert len(world.bus_config("dynamixel")["ids"]) == n
    emu = CanopenEmulator(world, interface="virtual", channel=f"papercut-{name}")  # refused before the fix
    assert len(emu.nodes) == n


def test_readme_jog_line_is_quoted_and_has_the_contact_input():
    text = README.read_text()
    lines = [ln for ln in text.splitlines() if ln.startswith("station jog ")]
    assert lines, "README lost its station jog example"
    for ln in lines:
        argv = shlex.split(ln)  # an unquoted & would end the command here (the shell backgrounds it)
        url = argv[argv.index("--robot") + 1]
        assert "&" in url and "contact=" in url, ln


def test_readme_serial_matches_the_example_world():
    import yaml
    from station.mocks.world.identity import default_serial

    # the serial the emulator reports for the example world: derived from the world (its arm and cell)
    world_serial = default_serial(World.from_dict(yaml.safe_load(example_text("ur5e"))))
    text = README.read_text()
    serials = set(re.findall(r"\b2023\d{7}\b", text))
    assert serials == {world_serial}, serials
