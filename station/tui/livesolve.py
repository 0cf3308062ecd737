"""The jog session's live solve: after every record, retake or discard the kept samples are solved for the
``--identify`` set (``station.solver.solve``), with what the technician must know to trust it: how many samples
were forced (recorded while the contact input was off: a pose, not a touch), whether the solver trusts its own
result, and each sample's residual after the fit (which touch to retake)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from station.robot.errors import StationError


@dataclass
class SolveState:
    status: str = "waiting"  # waiting | ok | error
    message: str = "no samples yet"
    n_samples: int = 0
    residuals: dict = field(default_factory=dict)
    identified: list[tuple[str, float, float | None, str]] = field(default_factory=list)  # name, value, std, unit
    unidentifiable: dict[str, str] = field(default_factory=dict)
    result: object | None = None  # CalibrationResult
    seconds: float = 0.0
    forced: int = 0  # samples recorded without contact (``!``)
    sample_residuals: dict[int, float] = field(default_factory=dict)  # journal seq -> |residual| after the fit (m)

    @property
    def trusted(self) -> bool:
        return self.result is None or bool(getattr(self.result, "trusted", True))

    @property
    def identified_ok(self) -> bool:
        """The solve may be shown as identified: it ran, the solver trusts it, and no sample was forced."""
        return self.status == "ok" and self.trusted and self.forced == 0

    @property
    def warning(self) -> str | None:
        """Why the numbers must not be taken as a calibration, in one line (None when they may)."""
        if self.status != "ok":
            return None
        if self.forced:
            who = ("every sample was forced" if self.forced == self.n_samples
                   else f"{self.forced} of {self.n_samples} samples forced")
            return f"{who} (recorded without contact): not identified; retake or discard them"
        if not self.trusted:
            failure = getattr(self.result, "failure", None) or "the solver does not trust this result"
            return f"not trusted: {failure}"
        return None


def is_forced(sample) -> bool:
    """Recorded with ``!`` while the contact input said no contact."""
    return bool((sample.status or {}).get("forced"))


def sample_residuals(model, result, samples, reference) -> dict[int, float]:
    """Distance (m) between each sample's tool position in the calibrated model and its point (solved, or
    given by ``--reference``): the touch that does not fit stands out."""
    points = dict(result.points())
    if isinstance(reference, dict):
        points.update({k: np.asarray(v, float) for k, v in reference.items()})
    try:
        p = result.calibrated(model).position(np.array([s.q for s in samples], float))
    except (ValueError, KeyError):
        return {}
    out = {}
    for s, x in zip(samples, p, strict=True):
        c = points.get(s.point)
        if c is not None and np.all(np.isfinite(c)):
            out[s.seq] = float(np.linalg.norm(x - c))
    return out


def live_solve(model, samples: list, identify: str, reference) -> SolveState:
    """Solve ``samples`` (journal ``Sample`` events) for ``identify``; never raises on bad data (the state says
    why). A cell with known distances or planes is not used here: the live solve is what the poses alone give."""
    if not samples:
        return SolveState()
    from station.solver import Observations, solve

    q = np.array([s.q for s in samples])
    labels = np.array([s.point for s in samples], dtype=object)
    forced = sum(is_forced(s) for s in samples)
    t0 = time.perf_counter()
    try:
        result = solve(model, Observations(q, labels), identify=identify, reference=reference)
    except (ValueError, KeyError, StationError, np.linalg.LinAlgError) as e:
        return SolveState("error", str(e), len(samples), seconds=time.perf_counter() - t0, forced=forced)
    dt = time.perf_counter() - t0
    identified = [(n, p.value - p.nominal if p.kind == "model" else p.value, p.std, p.unit)
                  for n, p in result.parameters.items() if p.identifiable]
    return SolveState("ok", "converged" if result.converged else "did not converge", len(samples),
                      dict(result.residuals), identified, dict(result.unidentifiable), result, dt, forced,
                      sample_residuals(model, result, samples, reference))
