"""Touch observations: joint readings, the label of the reference point touched, and optionally what an
external instrument measured. Arrays only, SI (rad, m); no file handling here (see ``station.samplesfile``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class SolverInputError(ValueError):
    """The data or the request cannot be solved as given (shapes, NaN, too few samples, unknown names)."""


@dataclass(frozen=True)
class Observations:
    """``q`` (N, n) encoder readings in SI; ``point`` (N,) labels of the fixed reference touched (one
    label ``"A"`` when omitted); ``measured`` (N, 3) tip positions in the instrument frame (m) or None.
    ``weight`` (N,) per-touch weights, 1/variance scale (a touch of weight w has noise sigma/sqrt(w); None:
    all 1). ``fixture`` (N,) fixture position labels: with more than one, each position has its own unknown
    points and planes (``A@F``), sharing the known distances (None: one position)."""

    q: np.ndarray
    point: np.ndarray | None = None
    measured: np.ndarray | None = None
    weight: np.ndarray | None = None
    fixture: np.ndarray | None = None

    def __post_init__(self) -> None:
        q = np.atleast_2d(np.asarray(self.q, dtype=float))
        if q.ndim != 2 or q.shape[0] == 0:
            raise SolverInputError(f"observations: q must be (N, n) with N >= 1, got shape {np.shape(self.q)}")
        bad = ~np.isfinite(q)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            raise SolverInputError(f"observations: sample {r}: q{c + 1} is not a finite number")
        n = q.shape[0]
        point = np.full(n, "A", dtype=object) if self.point is None else np.asarray(self.point, dtype=object)
        if point.shape != (n,):
            raise SolverInputError(f"observations: {n} samples but {point.size} point labels")
        point = np.array([str(p) for p in point], dtype=object)
        measured = self.measured
        if measured is not None:
            measured = np.asarray(measured, dtype=float)
            if measured.shape != (n, 3):
                raise SolverInputError(f"observations: measured must be ({n}, 3), got {measured.shape}")
            bad = ~np.isfinite(measured)
            if bad.any():
                r, c = np.argwhere(bad)[0]
                raise SolverInputError(f"observations: sample {r}: measured {'xyz'[c]} is not a finite number")
        weight = self.weight
        if weight is not None:
            weight = np.asarray(weight, dtype=float)
            if weight.shape != (n,):
                raise SolverInputError(f"observations: {n} samples but {weight.size} weights")
            bad = ~(np.isfinite(weight) & (weight > 0))
            if bad.any():
                r = int(np.flatnonzero(bad)[0])
                raise SolverInputError(f"observations: sample {r}: weight {weight[r]!r} is not a positive finite "
                                       "number")
        fixture = self.fixture
        if fixture is not None:
            fixture = np.asarray(fixture, dtype=object)
            if fixture.shape != (n,):
                raise SolverInputError(f"observations: {n} samples but {fixture.size} fixture labels")
            fixture = np.array([str(f) for f in fixture], dtype=object)
        object.__setattr__(self, "q", q)
        object.__setattr__(self, "point", point)
        object.__setattr__(self, "measured", measured)
        object.__setattr__(self, "weight", weight)
        object.__setattr__(self, "fixture", fixture)

    def __len__(self) -> int:
        return self.q.shape[0]

    @property
    def labels(self) -> list[str]:
        """Point labels in order of first appearance."""
        return list(dict.fromkeys(self.point.tolist()))

    @property
    def fixtures(self) -> list[str]:
        """Fixture position labels in order of first appearance ([] without a fixture column)."""
        return [] if self.fixture is None else list(dict.fromkeys(self.fixture.tolist()))

    @property
    def keys(self) -> np.ndarray:
        """(N,) the reference each touch is on: its label, or ``LABEL@FIXTURE`` with several fixtures."""
        if len(self.fixtures) <= 1:
            return self.point
        return np.array([f"{p}@{f}" for p, f in zip(self.point, self.fixture, strict=True)], dtype=object)

    @property
    def weights(self) -> np.ndarray:
        return np.ones(len(self)) if self.weight is None else self.weight

    def subset(self, mask) -> Observations:
        mask = np.asarray(mask)
        return Observations(self.q[mask], self.point[mask], None if self.measured is None else self.measured[mask],
                            None if self.weight is None else self.weight[mask],
                            None if self.fixture is None else self.fixture[mask])


def observations_from_samples(samples: list[dict]) -> tuple[Observations, Observations | None]:
    """Journal/records sample dicts (``{"point", "q", "measured", "set"}``, SI; see docs/architecture.md)
    -> (fit, holdout) observations split by ``set`` ("fit" unless "holdout"); holdout None when empty.
    Samples either all carry ``measured`` or none does."""
    if not samples:
        raise SolverInputError("no samples")
    fit, ho = [], []
    for i, s in enumerate(samples):
        try:
            q = [float(v) for v in s["q"]]
        except (KeyError, TypeError, ValueError):
            raise SolverInputError(f"sample {s.get('seq', i)}: no joint readings 'q'") from None
        try:
            w = float(s["weight"]) if s.get("weight") is not None else 1.0
        except (TypeError, ValueError):
            raise SolverInputError(f"sample {s.get('seq', i)}: weight {s.get('weight')!r} is not a number") from None
        fx = s.get("fixture")
        (ho if s.get("set") == "holdout" else fit).append(
            (q, str(s.get("point") or "A"), s.get("measured"), w, None if fx is None else str(fx)))
    with_m = {r[2] is not None for r in fit + ho}
    if len(with_m) > 1:
        raise SolverInputError("some samples carry instrument measurements and some do not")

    def build(rows):
        if not rows:
            return None
        meas = [r[2] for r in rows]
        w = np.array([r[3] for r in rows], dtype=float)
        fx = [r[4] for r in rows]
        return Observations(np.array([r[0] for r in rows]), np.array([r[1] for r in rows], dtype=object),
                            None if meas[0] is None else np.array(meas, dtype=float),
                            None if np.all(w == 1.0) else w,
                            None if all(f is None for f in fx) else np.array([f or "" for f in fx], dtype=object))

    out = build(fit)
    if out is None:
        raise SolverInputError("every sample is in the holdout set; nothing to fit")
    return out, build(ho)
