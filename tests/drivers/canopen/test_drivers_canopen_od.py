"""``station.drivers.canopen.od``: the standard objects the driver uses, with the data types and access CiA 301
and CiA 402 give them (CiA 402-2 object list; CiA 301 communication objects), read through python-canopen."""

from __future__ import annotations

import pytest
from canopen.objectdictionary import datatypes as dt
from station.drivers.canopen.od import master_od, standard_od

CIA = [  # index, name, type, access, PDO-mappable (CiA 402-2 / CiA 301)
    (0x1000, dt.UNSIGNED32, "ro", False), (0x1017, dt.UNSIGNED16, "rw", False),
    (0x603F, dt.UNSIGNED16, "ro", True), (0x6040, dt.UNSIGNED16, "rw", True), (0x6041, dt.UNSIGNED16, "ro", True),
    (0x6060, dt.INTEGER8, "rw", True), (0x6061, dt.INTEGER8, "ro", True), (0x6064, dt.INTEGER32, "ro", True),
    (0x6071, dt.INTEGER16, "rw", True), (0x607A, dt.INTEGER32, "rw", True), (0x6081, dt.UNSIGNED32, "rw", True),
    (0x60FD, dt.UNSIGNED32, "ro", True), (0x6502, dt.UNSIGNED32, "ro", False),
]


@pytest.mark.parametrize("index, dtype, access, pdo", CIA)
def test_standard_objects_as_cia_defines_them(index, dtype, access, pdo):
    v = standard_od(5)[index]
    assert (v.data_type, v.access_type, v.pdo_mappable) == (dtype, access, pdo)


def test_identity_and_pdo_parameters():
    d = standard_od(5)
    assert d.node_id == 5
    assert [d[0x1018][s].name for s in range(1, 5)] == ["Vendor-ID", "Product code", "Revision number",
                                                         "Serial number"]
    for base in (0x1400, 0x1800):  # 4 RPDOs and 4 TPDOs, each mapping up to 8 objects
        for n in range(4):
            assert d[base + n][1].data_type == dt.UNSIGNED32
            assert d[base + 0x200 + n][8].data_type == dt.UNSIGNED32
    m = master_od(127)
    assert m.node_id == 127 and m[0x1017].default == 0 and m[0x1000].default == 0  # a master, no profile
