"""``station.mocks.dynamixel.devices``: one emulated servo's control table with the access rules of the ROBOTIS
e-Manual (X-series, Protocol 2.0): the EEPROM area is writable only with the torque off, a write must cover whole
items, values outside an item's range or the position limits are refused with the e-Manual's error numbers
(4 data range, 5 data length, 6 data limit, 7 access), and a reboot returns the RAM to its defaults."""

from __future__ import annotations

import pytest
from station.mocks.dynamixel.devices import Device, WriteRefused
from station.mocks.dynamixel.tables import BY_NAME


def write(dev: Device, addr: int, value: int, size: int):
    dev.apply(dev.check_write(addr, int(value).to_bytes(size, "little", signed=value < 0)))


def refused(dev: Device, addr: int, value: int, size: int) -> int:
    with pytest.raises(WriteRefused) as e:
        write(dev, addr, value, size)
    return e.value.code


def test_control_table_rules():
    dev = Device(BY_NAME["xm430"], 11)
    assert dev.dxl_id == 11 and int.from_bytes(dev.read(0, 2), "little") == 1020  # model number XM430-W350
    write(dev, 20, -300, 4)  # Homing Offset (EEPROM) with the torque off
    assert refused(dev, 11, 2, 1) == 4  # operating mode 2 does not exist on an XM430
    write(dev, 64, 1, 1)  # Torque Enable
    assert refused(dev, 20, 0, 4) == 7  # EEPROM locked while the torque is on
    assert refused(dev, 116, 5000, 4) == 6  # Goal Position beyond Max Position Limit (4095) in position mode
    assert refused(dev, 116, 2048, 2) == 5  # half of Goal Position
    assert refused(dev, 132, 0, 4) == 7  # Present Position is read-only
    write(dev, 116, 3000, 4)
    assert int.from_bytes(dev.read(116, 4), "little") == 3000
    dev.reboot()  # RAM to defaults, EEPROM kept
    assert dev.torque is False and int.from_bytes(dev.read(116, 4), "little") == 0
    assert int.from_bytes(dev.read(20, 4), "little", signed=True) == -300
    image = dev.eeprom()
    again = Device(BY_NAME["xm430"], 11, image)  # a power cycle keeps the EEPROM
    assert int.from_bytes(again.read(20, 4), "little", signed=True) == -300
