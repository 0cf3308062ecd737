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
    label ``"A"`` when omitted); ``measured`` (N, 3) tip positions in the instrument frame (m) or None."""

    q: np.ndarray
    point: np.ndarray | None = None
    measured: np.ndarray | None = None

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
        object.__setattr__(self, "q", q)
        object.__setattr__(self, "point", point)
        object.__setattr__(self, "measured", measured)

    def __len__(self) -> int:
        return self.q.shape[0]

    @property
    def labels(self) -> list[str]:
        """Point labels in order of first appearance."""
        return list(dict.fromkeys(self.point.tolist()))

    def subset(self, mask) -> Observations:
        mask = np.asarray(mask)
        return Observations(self.q[mask], self.point[mask], None if self.measured is None else self.measured[mask])


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
        (ho if s.get("set") == "holdout" else fit).append((q, str(s.get("point") or "A"), s.get("measured")))
    with_m = {m is not None for _, _, m in fit + ho}
    if len(with_m) > 1:
        raise SolverInputError("some samples carry instrument measurements and some do not")

    def build(rows):
        if not rows:
            return None
        meas = [m for _, _, m in rows]
        return Observations(np.array([q for q, _, _ in rows]), np.array([p for _, p, _ in rows], dtype=object),
                            None if meas[0] is None else np.array(meas, dtype=float))

    out = build(fit)
    if out is None:
        raise SolverInputError("every sample is in the holdout set; nothing to fit")
    return out, build(ho)
