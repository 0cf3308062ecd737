"""``station.drivers.canopen.units``: a CiA 402 drive's position scaling checked against the model and its
velocity unit read (CiA 402 objects 0x608F/0x6091/0x6092, 0x60A8, 0x60A9), on an object dictionary of SDO
values (the bus below the SDO reads is not what this module is about; the emulated drives are tested with the
driver)."""

from __future__ import annotations

import math

import pytest
from station.drivers.canopen.units import UNIT_INC, UNIT_INC_PER_S, UNIT_RPM, exponent, read_units

from station.kinematics import load_model
from station.robot.errors import ConfigError, IdentityMismatch

ARM6 = load_model("arm6")  # encoder: 2^17 counts per motor revolution; joint 1 gear 121
MOTOR_REV = 2**17
JOINT_REV = MOTOR_REV * 121


class ObjectDictionary:
    """SDO values by (node, index, sub); absent objects read as None, as ``read_opt`` does."""

    def __init__(self, values: dict) -> None:
        self.values = values

    def read_opt(self, node, index, sub, kind):
        return self.values.get((node, index, sub), self.values.get((None, index, sub)))

    def per_node(self, nodes, fn):
        return {n: fn(n) for n in nodes}


def od(values=None, geared=False):
    """Objects every node answers alike; ``geared``: each node's 0x6091 gear as the model's joint has it."""
    out = {(None, i, s): v for (i, s), v in (values or {}).items()}
    if geared:
        for k, j in enumerate(ARM6.joints):
            out[(k + 1, 0x6091, 1)], out[(k + 1, 0x6091, 2)] = int(j.encoder.gear), 1
    return ObjectDictionary(out)


def test_exponent_is_the_signed_top_byte():
    assert exponent(0xFDB44700) == -3 and exponent(UNIT_RPM) == 0 and exponent(0x03B50300) == 3


def test_rpm_and_increments_per_second():
    nodes = [1, 2, 3, 4, 5, 6]
    rpm = read_units(od(values={(0x608F, 1): MOTOR_REV, (0x608F, 2): 1, (0x60A9, 0): 0xFDB44700}, geared=True),
                     ARM6, nodes)
    u = rpm[3]
    assert u.velocity_name == "0.001 rpm"
    # one unit of 0x6081 is 0.001 motor rev/min: 2^17 * 0.001 / 60 counts per second
    assert u.per_velocity_unit == pytest.approx(MOTOR_REV * 1e-3 / 60)
    assert u.velocity(MOTOR_REV) == 60_000  # one motor revolution per second = 60 rpm = 60000 x 0.001 rpm
    assert u.velocity(0.0) == 1  # never 0: a drive would take it literally
    inc = read_units(od(values={(0x60A9, 0): UNIT_INC_PER_S}), ARM6, nodes)[1]
    assert inc.per_velocity_unit == 1.0 and inc.velocity(1234.2) == 1235
    bare = read_units(od(), ARM6, nodes)[1]  # no 0x60A9: position units per second (CiA 402)
    assert bare.velocity_name == "increments/s"


@pytest.mark.parametrize("values, error, needle", [
    ({(0x60A8, 0): 0xFD410000}, ConfigError, "position unit 0x60A8 = 0xFD410000 is not encoder increments"),
    ({(0x60A9, 0): 0x00B40300}, ConfigError, "velocity unit 0x60A9 = 0x00B40300 is neither"),
    ({(0x608F, 1): 65536, (0x608F, 2): 1, (0x6091, 1): 121, (0x6091, 2): 1}, IdentityMismatch,
     "scaled 65536 counts/motor rev, gear 121:1 = 7929856 counts/rev but model arm6 says"),
    ({(0x6092, 1): JOINT_REV // 2, (0x6092, 2): 1}, IdentityMismatch, f"feed constant {JOINT_REV // 2}:1"),
])
def test_a_drive_counting_otherwise_is_refused_before_motion(values, error, needle):
    with pytest.raises(error) as e:
        read_units(od(values=values), ARM6, [1, 2, 3, 4, 5, 6])
    assert needle in str(e.value) and "nothing was moved" in str(e.value) and "canopen node 1 " in str(e.value)


def test_a_matching_feed_constant_passes():
    assert round(abs(ARM6.joints[0].encoder.counts_per_unit * 121) * 2 * math.pi) == JOINT_REV
    units = read_units(od(values={(0x6092, 1): JOINT_REV, (0x6092, 2): 1, (0x60A8, 0): UNIT_INC}), ARM6, [1])
    assert set(units) == {1}
