"""What every measuring instrument gives: its identity (who measured: a resumed session must use the same one)
and readings of the 6-DoF probe on the tool. SI: m, rotation vector in rad, the instrument's own frame."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable


@dataclass(frozen=True)
class PoseReading:
    """One stationary 6-DoF reading of the probe: position ``xyz`` (m) and rotation vector ``rv`` (rad) in the
    instrument's frame; ``t`` the instrument's clock (s)."""

    xyz: tuple[float, float, float]
    rv: tuple[float, float, float]
    t: float

    @property
    def pose(self) -> list[float]:
        return [*self.xyz, *self.rv]


@dataclass(frozen=True)
class InstrumentIdentity:
    """``serial`` and ``model`` name the instrument (another one measures in another frame); ``spec`` is what it
    states about itself (``sigma0_m``, ``sigma_per_m``: its per-axis noise, 1 sigma, at 0 m and per m of
    distance), ``kind`` what it is (``tracker``), ``protocol`` the wire protocol it spoke."""

    serial: str
    model: str | None = None
    kind: str = "instrument"
    protocol: str | None = None
    spec: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"serial": self.serial, "model": self.model, "kind": self.kind, "protocol": self.protocol,
                "spec": dict(self.spec)}

    def same_as(self, other: dict) -> bool:
        """Whether a journaled identity (``to_dict`` or the older ``{serial, spec: {model}}``) is this one."""
        model = other.get("model") or (other.get("spec") or {}).get("model")
        return (other.get("serial"), model) == (self.serial, self.model or self.spec.get("model"))

    def describe(self) -> str:
        model = self.model or self.spec.get("model")
        return f"serial {self.serial!r}" + (f" model {model!r}" if model else "")


@runtime_checkable
class PoseInstrument(Protocol):
    """An instrument that reads the tool's pose (a laser tracker with a 6-DoF probe)."""

    url: str

    def identity(self) -> InstrumentIdentity: ...

    def measure(self) -> PoseReading: ...

    def close(self) -> None: ...
