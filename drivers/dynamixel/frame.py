"""One servo's position frame: Goal / Present Position (ticks, the servo's registers) <-> the joint (SI).

What the servo reports depends on three settings of its own (ROBOTIS e-Manual, X-series control table):
- Drive Mode (10) bit 0, reverse mode: Goal and Present Position turn around; the Homing Offset keeps its sign
  ("In the case of Reverse Mode bit is set in Drive Mode(10), the sign of Homing Offset value will not be
  reversed");
- Homing Offset (20): ``Present Position = Actual Position + Homing Offset``; Position Control Mode (3) ignores
  one beyond +-1024;
- the turn count: Present Position is reset "to an absolute position value within one full rotation" at
  power-on, at a reboot, when the mode is switched to Position Control Mode and when the torque goes on in it
  (operating mode note), so the reading after such an event can be whole turns away from the one before.

With ``s`` = -1 in reverse mode and ``c`` the joint's encoder counts in the model's convention (``encoder``):
``Present = s * c + 4096 k + offset``. The station's joint reading (its raw ticks, model direction) is
``L = c + s * offset``: the model's encoder scaling gives ``q = q_raw + calibration``. The turn ``k`` is recovered
from the joint's range: the reading is unwrapped into the 4096-tick window centred on the joint limits, which is
unambiguous only when the joint spans less than one servo turn (checked at connect)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from station.drivers.dynamixel import table as T

TURN_MARGIN = 64  # ticks (5.6 deg) a joint may stand beyond its limits and still unwrap right


@dataclass
class ServoFrame:
    encoder: object  # station.kinematics.Encoder of the joint
    lower: float  # joint limits, SI
    upper: float
    sign: int = 1  # -1: Drive Mode reverse bit
    stored_offset: int = 0  # Homing Offset (20) as stored
    mode: int = T.MODE_POSITION  # Operating Mode (11)
    time_profile: bool = False  # Drive Mode bit 2: Profile Velocity / Acceleration in ms
    turn: int = 0  # the last reading's unwrap, in turns (-s k)

    @property
    def offset(self) -> int:
        """The homing offset the servo applies (ticks, its own frame)."""
        if self.mode == T.MODE_POSITION and abs(self.stored_offset) > T.HOMING_OFFSET_POSITION_MODE:
            return 0
        return self.stored_offset

    @property
    def offset_ticks(self) -> int:
        """The applied offset in the model's direction: what it adds to the joint reading."""
        return self.sign * self.offset

    def offset_limit(self) -> int:
        """The largest homing offset (ticks) this servo applies in its operating mode."""
        return T.HOMING_OFFSET_POSITION_MODE if self.mode == T.MODE_POSITION else T.HOMING_OFFSET_RANGE

    def count_range(self) -> tuple[float, float]:
        """The joint's limits in reading ticks (model direction, calibration included)."""
        a, b = float(self.encoder.to_counts(self.lower)), float(self.encoder.to_counts(self.upper))
        return min(a, b), max(a, b)

    def span_fits_one_turn(self) -> bool:
        lo, hi = self.count_range()
        return hi - lo + 2 * TURN_MARGIN < T.ONE_TURN

    def stays_in_one_turn(self) -> bool:
        """Position Control Mode covers one turn of the servo (0..4095): the joint's range, in the servo's frame,
        must not cross a turn boundary there (a goal beyond it would be out of the servo's range)."""
        lo, hi = self.count_range()
        a, b = sorted((self.sign * (lo - self.offset_ticks), self.sign * (hi - self.offset_ticks)))
        return math.floor(a / T.ONE_TURN) == math.floor(b / T.ONE_TURN)

    def reading(self, present: int) -> int:
        """Present Position -> the joint reading ``L`` (ticks, model direction, calibration included); remembers
        the turn for the next goal."""
        c0 = self.sign * (int(present) - self.offset)
        lo, hi = self.count_range()
        mid = 0.5 * (lo + hi) - self.offset_ticks
        self.turn = int(round((mid - c0) / T.ONE_TURN))
        return c0 + T.ONE_TURN * self.turn + self.offset_ticks

    def goal(self, reading: float) -> int:
        """The joint reading ``L`` to reach -> Goal Position in the servo's frame (the turn of the last reading)."""
        c = float(reading) - self.offset_ticks
        return int(round(self.sign * (c - T.ONE_TURN * self.turn) + self.offset))

    def to_si(self, reading: float) -> float:
        return float(self.encoder.to_si(reading))

    def to_reading(self, q: float) -> int:
        return int(round(float(self.encoder.to_counts(q))))

    def offset_si(self, offset_ticks: int) -> float:
        """An offset in reading ticks (model direction) -> SI."""
        e = self.encoder
        return float(e.to_si(offset_ticks + e.zero) - e.to_si(e.zero))

    def offset_from_si(self, value: float) -> int:
        """An offset in SI -> the Homing Offset to store (ticks, servo frame: reverse mode turns it around)."""
        e = self.encoder
        ticks = int(round(float(value) * e.counts_per_unit * e.gear * e.direction))
        return self.sign * ticks


def describe_mode(mode: int) -> str:
    return f"{mode} ({T.MODE_NAMES.get(mode, 'unknown')})"


def time_profile(duration: float, accel_time: float) -> tuple[int, int]:
    """(Profile Acceleration, Profile Velocity) in ms for a time-based profile: the move takes ``duration`` s and
    accelerates for ``accel_time`` s (at most half of it, as the servo enforces)."""
    pv = max(1, math.ceil(duration * 1000.0))
    pa = max(0, min(pv // 2, math.floor(accel_time * 1000.0)))
    return pa, pv
