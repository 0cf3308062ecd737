"""The object dictionary the station driver needs: standard CiA 301 / CiA 402 objects only.

The driver works with any CiA 402 drive, so it does not need the vendor's EDS (pass ``eds=FILE`` in the
URL to use one instead). Positions are motor encoder counts, velocities counts/s, torque per mille."""

from __future__ import annotations

from canopen import objectdictionary as od
from canopen.objectdictionary import datatypes as dt

CONTACT_WIRED = 0x2000  # manufacturer object of the station's emulated drive: 1 = 0x60FD bit 16 is the cell input


def _var(name: str, index: int, sub: int, dtype: int, access: str = "rw", pdo: bool = False) -> od.ODVariable:
    v = od.ODVariable(name, index, sub)
    v.data_type = dtype
    v.access_type = access
    v.pdo_mappable = pdo
    return v


def _record(name: str, index: int, subs: list[tuple[int, str, int, str]], array: bool = False):
    obj = od.ODArray(name, index) if array else od.ODRecord(name, index)
    for sub, sub_name, dtype, access in subs:
        obj.add_member(_var(sub_name, index, sub, dtype, access))
    return obj


def standard_od(node_id: int) -> od.ObjectDictionary:
    d = od.ObjectDictionary()
    d.node_id = node_id
    U8, U16, U32, I8, I16, I32, STR = (dt.UNSIGNED8, dt.UNSIGNED16, dt.UNSIGNED32, dt.INTEGER8, dt.INTEGER16,
                                        dt.INTEGER32, dt.VISIBLE_STRING)
    for obj in (
        _var("Device type", 0x1000, 0, U32, "ro"),
        _var("Error register", 0x1001, 0, U8, "ro", True),
        _var("Manufacturer device name", 0x1008, 0, STR, "const"),
        _var("Manufacturer hardware version", 0x1009, 0, STR, "const"),
        _var("Manufacturer software version", 0x100A, 0, STR, "const"),
        _record("Store parameters", 0x1010, [(0, "Highest sub-index supported", U8, "const"),
                                             (1, "Save all parameters", U32, "rw"),
                                             (2, "Save communication parameters", U32, "rw"),
                                             (3, "Save application parameters", U32, "rw")], array=True),
        _var("Producer heartbeat time", 0x1017, 0, U16),
        _record("Identity object", 0x1018, [(0, "Highest sub-index supported", U8, "const"),
                                            (1, "Vendor-ID", U32, "ro"), (2, "Product code", U32, "ro"),
                                            (3, "Revision number", U32, "ro"), (4, "Serial number", U32, "ro")]),
        _var("Contact input wired", CONTACT_WIRED, 0, U8, "ro"),
        _var("Error code", 0x603F, 0, U16, "ro", True),
        _var("Controlword", 0x6040, 0, U16, "rw", True),
        _var("Statusword", 0x6041, 0, U16, "ro", True),
        _var("Modes of operation", 0x6060, 0, I8, "rw", True),
        _var("Modes of operation display", 0x6061, 0, I8, "ro", True),
        _var("Position actual value", 0x6064, 0, I32, "ro", True),
        _var("Target torque", 0x6071, 0, I16, "rw", True),
        _var("Target position", 0x607A, 0, I32, "rw", True),
        _var("Home offset", 0x607C, 0, I32),
        _var("Profile velocity", 0x6081, 0, U32, "rw", True),
        _var("Digital inputs", 0x60FD, 0, U32, "ro", True),
        _var("Supported drive modes", 0x6502, 0, U32, "ro"),
    ):
        d.add_object(obj)
    for base, kind in ((0x1400, "RPDO"), (0x1800, "TPDO")):
        for n in range(4):
            d.add_object(_record(f"{kind}{n + 1} communication parameter", base + n, [
                (0, "Highest sub-index supported", U8, "const"), (1, f"COB-ID used by {kind}", U32, "rw"),
                (2, "Transmission type", U8, "rw"), (3, "Inhibit time", U16, "rw"), (5, "Event timer", U16, "rw"),
            ]))
            d.add_object(_record(f"{kind}{n + 1} mapping parameter", base + 0x200 + n,
                                 [(0, "Number of mapped objects", U8, "rw")]
                                 + [(k, f"Mapped object {k}", U32, "rw") for k in range(1, 9)], array=True))
    return d


def master_od(node_id: int) -> od.ObjectDictionary:
    """The station's own node on the bus (a ``canopen.LocalNode``): a CiA 301 heartbeat producer, so each drive's
    heartbeat consumer (0x1016) can watch the station and stop its joint when the station is gone."""
    d = od.ObjectDictionary()
    d.node_id = node_id
    for obj in (
        _var("Device type", 0x1000, 0, dt.UNSIGNED32, "ro"),
        _var("Error register", 0x1001, 0, dt.UNSIGNED8, "ro"),
        _var("Producer heartbeat time", 0x1017, 0, dt.UNSIGNED16),
    ):
        d.add_object(obj)
    d[0x1000].default = 0  # a master, no device profile
    d[0x1001].default = 0
    d[0x1017].default = 0
    return d
