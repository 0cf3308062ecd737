"""Generator of the shipped EDS of the emulated CiA 402 servo drive (``drive402.eds``).

The EDS is the contract between the emulator (``canopen.LocalNode`` loads it) and the station driver
(``canopen.BaseNode402`` loads the same file). Regenerate after editing ``OBJECTS``:

    .venv/bin/python -m station.mocks.canopen.eds          # rewrites mocks/canopen/drive402.eds
    .venv/bin/python -m station.mocks.canopen.eds --check  # exit 1 if the shipped file is stale

Units: positions in motor encoder counts, velocities in counts/s, accelerations in counts/s^2,
torques in per mille of rated torque, times in ms (heartbeat, event timer) or 100 us (inhibit time).
``StorageLocation`` says what "store parameters" (0x1010) persists: PERSIST_COMM (0x1000-0x1FFF),
PERSIST_APP (0x6000-0x9FFF), PERSIST_MFR (0x2000-0x5FFF); RAM objects are volatile.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

EDS_PATH = Path(__file__).resolve().parent / "drive402.eds"

# data types (CiA 301)
I8, I16, I32, U8, U16, U32, STR = 0x2, 0x3, 0x4, 0x5, 0x6, 0x7, 0x9

VENDOR_ID = 0x00000A5E  # emulated vendor ("station"), not a registered CiA vendor id
PRODUCT_CODE = 0x00402001
REVISION = 0x00010002
DEVICE_NAME = "STN-402 emulated servo drive"
HW_VERSION = "EMU-1"
SW_VERSION = "1.2.0"
CONTACT_INPUT_BIT = 16  # manufacturer-specific bit of 0x60FD wired to the cell's contact input
SUPPORTED_MODES = 0x0000002D  # profile position (bit 0), profile velocity (bit 2), profile torque (bit 3), homing (5)
SAVE_SIGNATURE = 0x65766173  # "save" as little-endian UNSIGNED32 (CiA 301 0x1010)
LOAD_SIGNATURE = 0x64616F6C  # "load" (CiA 301 0x1011)
POSITION_OFFSET = 0x2001  # manufacturer object: the homing result (0x6064 - 0x6063), stored with the application
# SI unit codes (0x60A8/0x60A9): exponent (bits 24-31), unit (16-23), time unit (8-15). rpm: Synapticon 0x60A9,
# Nanotec PD6-C 60A9h preset; increments and increments/s: the station's emulated drive's own coding
UNIT_INC = 0x00B50000
UNIT_INC_PER_S = 0x00B50300
UNIT_RPM = 0x00B44700
DEFAULT_TORQUE_LIMIT = 3000  # per mille of rated torque: a servo's peak torque (0x6072, 0x60E0, 0x60E1)


@dataclass(frozen=True)
class Var:
    sub: int
    name: str
    dtype: int
    access: str
    default: str | int
    pdo: bool = False
    storage: str = "RAM"


@dataclass(frozen=True)
class Obj:
    index: int
    name: str
    kind: int  # 7 VAR, 8 ARRAY, 9 RECORD
    subs: tuple[Var, ...]


def var(index: int, name: str, dtype: int, access: str, default, pdo: bool = False, storage: str = "RAM") -> Obj:
    return Obj(index, name, 7, (Var(0, name, dtype, access, default, pdo, storage),))


def _pdo_objects() -> list[Obj]:
    # Default mapping ("pre-defined connection set" style), used until a master remaps by SDO.
    rpdo_maps = {0: [(0x6040, 0, 16), (0x607A, 0, 32)], 1: [(0x6060, 0, 8), (0x6081, 0, 32), (0x6071, 0, 16)]}
    tpdo_maps = {0: [(0x6041, 0, 16), (0x6064, 0, 32), (0x6061, 0, 8)], 1: [(0x60FD, 0, 32), (0x603F, 0, 16)]}
    out: list[Obj] = []
    for n in range(4):
        cob = f"$NODEID+0x{0x200 + 0x100 * n:X}" if n in rpdo_maps else f"0x{0x80000000 + 0x200 + 0x100 * n:X}"
        out.append(Obj(0x1400 + n, f"RPDO{n + 1} communication parameter", 9, (
            Var(0, "Highest sub-index supported", U8, "const", 5),
            Var(1, "COB-ID used by RPDO", U32, "rw", cob, storage="PERSIST_COMM"),
            Var(2, "Transmission type", U8, "rw", 255, storage="PERSIST_COMM"),
            Var(3, "Inhibit time", U16, "rw", 0, storage="PERSIST_COMM"),
            Var(5, "Event timer", U16, "rw", 0, storage="PERSIST_COMM"),
        )))
    for n in range(4):
        entries = rpdo_maps.get(n, [])
        out.append(Obj(0x1600 + n, f"RPDO{n + 1} mapping parameter", 8, (
            Var(0, "Number of mapped objects", U8, "rw", len(entries), storage="PERSIST_COMM"),
            *(Var(k + 1, f"Mapped object {k + 1}", U32, "rw",
                  (entries[k][0] << 16 | entries[k][1] << 8 | entries[k][2]) if k < len(entries) else 0,
                  storage="PERSIST_COMM") for k in range(8)),
        )))
    for n in range(4):
        base = 0x180 + 0x100 * n
        cob = f"$NODEID+0x{base:X}" if n in tpdo_maps else f"0x{0x80000000 + base:X}"
        trans, timer = (1, 0) if n == 0 else (255, 100)
        out.append(Obj(0x1800 + n, f"TPDO{n + 1} communication parameter", 9, (
            Var(0, "Highest sub-index supported", U8, "const", 6),
            Var(1, "COB-ID used by TPDO", U32, "rw", cob, storage="PERSIST_COMM"),
            Var(2, "Transmission type", U8, "rw", trans, storage="PERSIST_COMM"),
            Var(3, "Inhibit time", U16, "rw", 0, storage="PERSIST_COMM"),
            Var(5, "Event timer", U16, "rw", timer, storage="PERSIST_COMM"),
            Var(6, "SYNC start value", U8, "rw", 0, storage="PERSIST_COMM"),
        )))
    for n in range(4):
        entries = tpdo_maps.get(n, [])
        out.append(Obj(0x1A00 + n, f"TPDO{n + 1} mapping parameter", 8, (
            Var(0, "Number of mapped objects", U8, "rw", len(entries), storage="PERSIST_COMM"),
            *(Var(k + 1, f"Mapped object {k + 1}", U32, "rw",
                  (entries[k][0] << 16 | entries[k][1] << 8 | entries[k][2]) if k < len(entries) else 0,
                  storage="PERSIST_COMM") for k in range(8)),
        )))
    return out


def _pair(index: int, name: str, dtype: int, first: tuple[str, int], second: tuple[str, int]) -> Obj:
    """A CiA 402 record of two stored rw entries (sub 1, sub 2) of one type, e.g. 0x607D min/max limit."""
    return Obj(index, name, 8, (
        Var(0, "Highest sub-index supported", U8, "const", 2),
        *(Var(k, sub, dtype, "rw", default, storage="PERSIST_APP")
          for k, (sub, default) in enumerate((first, second), 1)),
    ))


def objects() -> list[Obj]:
    """The drive's object dictionary, in index order."""
    return [*_communication_objects(), *_pdo_objects(), *_manufacturer_objects(), *_profile_objects()]


def _communication_objects() -> list[Obj]:
    """CiA 301 communication profile area (0x1000-0x1029) without the PDO parameters."""
    C = "PERSIST_COMM"
    return [
        var(0x1000, "Device type", U32, "ro", 0x00020192),  # CiA 402, servo drive
        var(0x1001, "Error register", U8, "ro", 0, pdo=True),
        Obj(0x1003, "Pre-defined error field", 8, (
            Var(0, "Number of errors", U8, "rw", 0),
            *(Var(k, f"Standard error field {k}", U32, "ro", 0) for k in range(1, 9)),
        )),
        var(0x1005, "COB-ID SYNC message", U32, "rw", 0x80, storage=C),
        var(0x1008, "Manufacturer device name", STR, "const", DEVICE_NAME),
        var(0x1009, "Manufacturer hardware version", STR, "const", HW_VERSION),
        var(0x100A, "Manufacturer software version", STR, "const", SW_VERSION),
        Obj(0x1010, "Store parameters", 8, (
            Var(0, "Highest sub-index supported", U8, "const", 4),
            Var(1, "Save all parameters", U32, "rw", 1),
            Var(2, "Save communication parameters", U32, "rw", 1),
            Var(3, "Save application parameters", U32, "rw", 1),
            Var(4, "Save manufacturer parameters", U32, "rw", 1),
        )),
        Obj(0x1011, "Restore default parameters", 8, (
            Var(0, "Highest sub-index supported", U8, "const", 1),
            Var(1, "Restore all default parameters", U32, "rw", 1),
        )),
        var(0x1014, "COB-ID EMCY", U32, "rw", "$NODEID+0x80", storage=C),
        Obj(0x1016, "Consumer heartbeat time", 8, (
            Var(0, "Highest sub-index supported", U8, "const", 4),
            *(Var(k, f"Consumer heartbeat time {k}", U32, "rw", 0, storage=C) for k in range(1, 5)),
        )),
        var(0x1017, "Producer heartbeat time", U16, "rw", 0, storage=C),
        Obj(0x1018, "Identity object", 9, (
            Var(0, "Highest sub-index supported", U8, "const", 4),
            Var(1, "Vendor-ID", U32, "ro", VENDOR_ID),
            Var(2, "Product code", U32, "ro", PRODUCT_CODE),
            Var(3, "Revision number", U32, "ro", REVISION),
            Var(4, "Serial number", U32, "ro", 0),
        )),
        Obj(0x1029, "Error behaviour", 8, (
            Var(0, "Highest sub-index supported", U8, "const", 1),
            Var(1, "Communication error", U8, "rw", 0, storage=C),  # 0: OPERATIONAL -> PRE-OPERATIONAL
        )),
    ]


def _manufacturer_objects() -> list[Obj]:
    return [
        var(0x2000, "Contact input wired", U8, "ro", 0),  # 1: bit 16 of 0x60FD follows the cell contact
        # the homing result (position actual - position actual internal value); stored with the application
        # parameters (0x1010:03) so that an absolute encoder keeps its zero across power cycles
        var(POSITION_OFFSET, "Position offset", I32, "ro", 0, storage="PERSIST_APP"),
    ]


def _profile_objects() -> list[Obj]:
    """CiA 402 drive profile area (0x6000-): what the station's driver and the emulated drive exchange."""
    A = "PERSIST_APP"
    return [
        var(0x603F, "Error code", U16, "ro", 0, pdo=True),
        var(0x6007, "Abort connection option code", I16, "rw", 0, storage=A),
        var(0x6040, "Controlword", U16, "rw", 0, pdo=True),
        var(0x6041, "Statusword", U16, "ro", 0, pdo=True),
        var(0x605A, "Quick stop option code", I16, "rw", 2, storage=A),
        var(0x6060, "Modes of operation", I8, "rw", 0, pdo=True),
        var(0x6061, "Modes of operation display", I8, "ro", 0, pdo=True),
        var(0x6062, "Position demand value", I32, "ro", 0, pdo=True),
        var(0x6063, "Position actual internal value", I32, "ro", 0, pdo=True),
        var(0x6064, "Position actual value", I32, "ro", 0, pdo=True),
        var(0x6065, "Following error window", U32, "rw", 100000, storage=A),
        var(0x6067, "Position window", U32, "rw", 50, storage=A),
        var(0x6068, "Position window time", U16, "rw", 0, storage=A),
        var(0x606C, "Velocity actual value", I32, "ro", 0, pdo=True),
        var(0x6071, "Target torque", I16, "rw", 0, pdo=True),
        var(0x6072, "Max torque", U16, "rw", DEFAULT_TORQUE_LIMIT, storage=A),
        var(0x6076, "Motor rated torque", U32, "ro", 1000),  # mN m, set per drive from the world's joint
        var(0x6077, "Torque actual value", I16, "ro", 0, pdo=True),
        var(0x607A, "Target position", I32, "rw", 0, pdo=True),
        var(0x607C, "Home offset", I32, "rw", 0, storage=A),
        _pair(0x607D, "Software position limit", I32, ("Min position limit", 0), ("Max position limit", 0)),
        var(0x607F, "Max profile velocity", U32, "rw", 0, storage=A),
        var(0x6081, "Profile velocity", U32, "rw", 0, pdo=True, storage=A),
        var(0x6083, "Profile acceleration", U32, "rw", 0, storage=A),
        var(0x6084, "Profile deceleration", U32, "rw", 0, storage=A),
        var(0x6085, "Quick stop deceleration", U32, "rw", 0, storage=A),
        var(0x6087, "Torque slope", U32, "rw", 1000, storage=A),
        # scaling (CiA 402): encoder increments per motor revolution and gear ratio motor : shaft revolutions,
        # set per drive from the world's joint (rotary joints); the driver checks them against its model
        _pair(0x608F, "Position encoder resolution", U32, ("Encoder increments", 0), ("Motor revolutions", 1)),
        _pair(0x6091, "Gear ratio", U32, ("Motor revolutions", 1), ("Shaft revolutions", 1)),
        var(0x6098, "Homing method", I8, "rw", 0, storage=A),  # 0: none assigned; 35/37: current position
        var(0x60A8, "SI unit position", U32, "rw", UNIT_INC, storage=A),
        var(0x60A9, "SI unit velocity", U32, "rw", UNIT_INC_PER_S, storage=A),
        var(0x60E0, "Positive torque limit value", U16, "rw", DEFAULT_TORQUE_LIMIT, pdo=True, storage=A),
        var(0x60E1, "Negative torque limit value", U16, "rw", DEFAULT_TORQUE_LIMIT, pdo=True, storage=A),
        var(0x60FD, "Digital inputs", U32, "ro", 0, pdo=True),
        var(0x60FF, "Target velocity", I32, "rw", 0, pdo=True),
        var(0x6502, "Supported drive modes", U32, "ro", SUPPORTED_MODES),
    ]


def _fmt(v) -> str:
    return v if isinstance(v, str) else f"0x{v:X}" if v >= 0 else str(v)


def _var_lines(section: str, v: Var) -> list[str]:
    lines = [f"[{section}]", f"ParameterName={v.name}", "ObjectType=0x7", f"DataType=0x{v.dtype:04X}",
             f"AccessType={v.access}", f"DefaultValue={_fmt(v.default)}", f"PDOMapping={int(v.pdo)}"]
    if v.storage != "RAM":
        lines.append(f"StorageLocation={v.storage}")
    return lines + [""]


def generate() -> str:
    objs = objects()
    mandatory = [o for o in objs if o.index in (0x1000, 0x1001, 0x1018)]
    optional = [o for o in objs if o.index < 0x2000 and o not in mandatory] + [o for o in objs if o.index >= 0x6000]
    mfr = [o for o in objs if 0x2000 <= o.index < 0x6000]
    out = [
        "; Generated by station.mocks.canopen.eds -- do not edit by hand; edit OBJECTS and regenerate.",
        "; Positions: motor encoder counts; velocities: counts/s; torques: per mille of rated torque.",
        "[FileInfo]", "FileName=drive402.eds", "FileVersion=1", "FileRevision=2", "EDSVersion=4.0",
        "Description=Emulated CiA 402 servo drive of the station project", "CreatedBy=station", "",
        "[DeviceInfo]", "VendorName=station (emulated)", f"VendorNumber=0x{VENDOR_ID:08X}",
        f"ProductName={DEVICE_NAME}", f"ProductNumber=0x{PRODUCT_CODE:08X}", f"RevisionNumber=0x{REVISION:08X}",
        "OrderCode=STN-402-EMU", *(f"BaudRate_{b}=1" for b in (125, 250, 500, 1000)),
        *(f"BaudRate_{b}=0" for b in (10, 20, 50, 800)),
        "SimpleBootUpMaster=0", "SimpleBootUpSlave=1", "Granularity=8", "DynamicChannelsSupported=0",
        "GroupMessaging=0", "NrOfRXPDO=4", "NrOfTXPDO=4", "LSS_Supported=0", "",
        "[DummyUsage]", *(f"Dummy{i:04d}=0" for i in range(1, 8)), "",
    ]
    for title, group in (("MandatoryObjects", mandatory), ("OptionalObjects", optional),
                         ("ManufacturerObjects", mfr)):
        out += [f"[{title}]", f"SupportedObjects={len(group)}"]
        out += [f"{k}=0x{o.index:04X}" for k, o in enumerate(group, 1)] + [""]
    for o in mandatory + optional + mfr:
        if o.kind == 7:
            out += _var_lines(f"{o.index:04X}", o.subs[0])
            continue
        out += [f"[{o.index:04X}]", f"ParameterName={o.name}", f"ObjectType=0x{o.kind:X}",
                f"SubNumber={len(o.subs)}", ""]
        for v in o.subs:
            out += _var_lines(f"{o.index:04X}sub{v.sub:X}", v)
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    text = generate()
    if "--check" in argv:
        stale = not EDS_PATH.exists() or EDS_PATH.read_text() != text
        print(f"{EDS_PATH}: {'stale, regenerate' if stale else 'up to date'}")
        return int(stale)
    EDS_PATH.write_text(text)
    print(f"wrote {EDS_PATH}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
