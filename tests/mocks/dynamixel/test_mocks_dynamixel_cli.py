"""``station.mocks.dynamixel.cli``: the emulator a world file and the command's options make (options win over
the world's ``buses.dynamixel``), and its EEPROM file kept across runs."""

from __future__ import annotations

import pytest
from station.mocks.dynamixel.cli import _load_eeprom, _save_eeprom, emulator_for
from station.mocks.errors import MockError
from station.mocks.world import World


def test_options_win_over_the_world_file():
    doc_world = World.default(model="omx", seed=1)
    emu = emulator_for(doc_world, ids="11-14", contact_id="off")
    assert emu.joint_ids == [11, 12, 13, 14] and emu.contact_id is None
    assert emulator_for(doc_world).joint_ids == [1, 2, 3, 4]  # the defaults: ids 1..n
    with pytest.raises(MockError, match="bad servo id list '4-1'"):
        emulator_for(doc_world, ids="4-1")


def test_eeprom_images_round_trip(tmp_path):
    f = tmp_path / "eeprom.json"
    images = {11: bytes(range(64)), 3: b"\x00" * 64}
    _save_eeprom(f, images)
    assert _load_eeprom(f) == images and _load_eeprom(tmp_path / "none.json") == {}
    f.write_text('{"eeprom": {"x": "zz"}}')
    with pytest.raises(MockError, match="not a dynamixel EEPROM file"):
        _load_eeprom(f)
