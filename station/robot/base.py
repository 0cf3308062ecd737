"""``RobotBase``: what every driver shares, so each one writes only what its bus does differently (python-can's
``BusABC`` idea).

- lifecycle (``station.plugins.CloseOnce``, shared with instruments): ``close()`` runs the driver's
  ``_shutdown()`` exactly once (also on a robot whose constructor failed half way), ``with robot:`` closes it,
  ``closed`` says so, motion on a closed robot is refused;
- URL options: the class declares ``options`` (``station.robot.url.Options``); ``from_url`` parses them;
- motion pre-checks before anything is sent: joint limits, speed values, no motion while compliant, jog
  targets and the 250 mm/s tool cap (``station.robot.motion``).

Drivers subclass it; callers never need to: they use the ``Robot`` protocol and the capability protocols."""

from __future__ import annotations

import math
from abc import abstractmethod
from typing import TYPE_CHECKING, ClassVar

from station.plugins import CloseOnce
from station.robot.errors import ConfigError, ConnectionLost, LimitError, SafetyStop
from station.robot.url import Option, Options, RobotURL, text

if TYPE_CHECKING:
    import numpy as np

    from station.kinematics import Model


# Every driver's URL takes these next to ``model=`` (a URDF with several chain ends needs its tip named).
CHAIN_OPTIONS = (
    Option("tip_link", text(), None, "URDF model: the link the tool is on", default_doc="the end of the only chain"),
    Option("base_link", text(), None, "URDF model: the link the chain starts from", default_doc="the root link"),
)


class RobotBase(CloseOnce):
    options: ClassVar[Options] = Options()  # the URL query options this driver accepts
    noun: ClassVar[str] = "robot"
    closed_error: ClassVar[type[Exception]] = ConnectionLost
    model: Model
    _compliant: bool = False  # class default: valid before the constructor ran (close() of a half-built robot)

    # ---- construction ------------------------------------------------------------------------------------
    @classmethod
    @abstractmethod
    def from_url(cls, url: RobotURL, **overrides) -> RobotBase:
        """A connected robot for ``url`` (``cls.options.parse(url)`` gives the option values);
        ``overrides`` replace constructor arguments (scripts, tests)."""

    @staticmethod
    def load_url_model(url: RobotURL, name_or_model, tip_link: str | None = None, base_link: str | None = None):
        """The kinematic model a URL names (``model=``, with ``tip_link=``/``base_link=`` choosing the chain of a
        URDF), a ``ConfigError`` naming the URL if it cannot load."""
        from station.kinematics import Model, ModelFileError, load_model

        if isinstance(name_or_model, Model):
            return name_or_model
        try:
            return load_model(name_or_model, tip_link=tip_link, base_link=base_link)
        except (ModelFileError, OSError, ValueError, KeyError) as e:
            raise ConfigError(f"robot URL {url.raw!r}: model {name_or_model!r}: {e}") from None

    # ---- lifecycle (close-once: station.plugins.CloseOnce) ---------------------------------------------------
    @abstractmethod
    def _shutdown(self) -> None:
        """Leave every device in its safe state (stopped, holding or powered down) and release the bus.
        Runs once, possibly on a half-constructed robot; must not raise for a bus that is already gone."""

    # ---- motion pre-checks (nothing is sent when one fails) ----------------------------------------------
    def _check_stiff(self, what: str) -> None:
        if self._compliant:
            raise SafetyStop(f"{what}: the robot is compliant (set_compliant(False) first); nothing was sent")

    def _checked_target(self, q, what: str) -> np.ndarray:
        """``q`` as an array within the model's joint limits (``LimitError`` naming the joint otherwise)."""
        from station.robot.motion import check_joint_limits

        self._check_open(what)
        return check_joint_limits(self.model, q, what)

    @staticmethod
    def _checked_speed(speed: float | None, what: str, unit: str = "rad/s", upper: float | None = None
                       ) -> float | None:
        """``None`` (the driver's default) or a finite speed > 0 (and <= ``upper``); ``LimitError`` otherwise."""
        if speed is None:
            return None
        try:
            v = float(speed)
        except (TypeError, ValueError):
            v = math.nan
        if not (math.isfinite(v) and v > 0):
            raise LimitError(f"{what}: speed must be a positive number of {unit}, got {speed!r}; nothing was sent")
        if upper is not None and v > upper:
            raise LimitError(f"{what}: speed {v:g} {unit} outside (0, {upper:g}] {unit}; nothing was sent")
        return v

    def _jog_target(self, q0: np.ndarray, mode: str, axis: int, step: float) -> np.ndarray:
        """Joint target of one jog step from ``q0`` (``station.robot.motion.jog_target``), within limits."""
        from station.robot.motion import jog_target

        self._check_open("jog")
        try:
            finite = math.isfinite(float(step))
        except (TypeError, ValueError):
            finite = False
        if not finite:
            raise LimitError(f"jog: step must be finite, got {step!r}; nothing was sent")
        return jog_target(self.model, q0, mode, axis, step)

    def _jog_plan(self, q0: np.ndarray, mode: str, axis: int, step: float, speed: float | None, *,
                  joint_default: float | None, tool_default: float) -> tuple[np.ndarray, float]:
        """Target of one jog step and the lead joint's speed for it: a Cartesian step at ``speed`` m/s at the
        tool (default ``tool_default``, never above 0.25 m/s), a joint step at ``speed`` rad/s (default
        ``joint_default``, ``None``: the joint's maximum) slowed so the tool stays within 0.25 m/s."""
        from station.robot.motion import MANUAL_TOOL_SPEED_CAP, joint_speed_for_tool_cap

        target = self._jog_target(q0, mode, axis, step)
        if mode == "cartesian":
            cap = self._checked_speed(speed, "jog", "m/s", MANUAL_TOOL_SPEED_CAP) or tool_default
            return target, joint_speed_for_tool_cap(self.model, q0, target, None, cap=cap)
        requested = self._checked_speed(speed, "jog")
        return target, joint_speed_for_tool_cap(self.model, q0, target, requested or joint_default)
