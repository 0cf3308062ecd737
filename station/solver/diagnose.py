"""Post-fit diagnosis of a solve that cannot be signed: pure, arrays in, one line out.

* :func:`noise_free`: a fit with (numerically) no residual gives an uncertainty of ~0 — the noise cannot be
  estimated from data that have none (synthetic or copied samples), so a ± of 0 must never be printed as if it
  were measured. The caller refuses the ± unless the instrument noise is declared (``--noise``).
* :func:`unit_slip`: a fit far above any touch noise may come from a unit mix-up that stays inside the joint
  limits (so the samples reader cannot see it): one column ×1000 or ÷1000 (mm/m, mrad/rad), one column or one
  row in degrees under a radian header (or the reverse). Each hypothesis is tried by rescaling the readings and
  solving again (``refit``); one that brings the residual down to the noise names the column or row and the
  likely unit. The solver is never asked to guess silently: the caller refuses the input (exit 2)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from station.solver.observations import Observations
from station.solver.result import CalibrationResult

# below this fitted residual (m per axis) the data are noise-free: no touch instrument, seat or tracker is
# better than 0.1 um, so the residual is rounding, and an uncertainty computed from it is not a measurement
NOISE_FREE_M = 1e-7
# a fitted residual above this (m per axis) is far above any touch station's noise (seats ~10 um, a UR's
# repetability 30 um): worth looking for a unit slip when no noise was declared
FAR_ABOVE_M = 0.5e-3
# a hypothesis explains the misfit when it cuts the residual at least this much and lands at the noise
GAIN = 20.0
MAX_ROWS = 8  # rows tried one by one (excluded outliers, then the worst fitted): bounded cost on large files

DEG = math.pi / 180.0


@dataclass(frozen=True)
class Slip:
    where: str  # "column q3" / "row 7"
    factor: float  # what the readings must be multiplied by to fit
    unit: str  # the likely unit, in words
    rms_m: float  # residual RMS with the hypothesis, m
    rms0_m: float  # misfit as read (fit RMS, or the excluded row's residual), m

    def message(self) -> str:
        return (f"{self.where}: {self.unit} (misfit {self.rms0_m * 1e3:.4g} mm; rescaled ×{self.factor:.6g} the "
                f"fit is {self.rms_m * 1e3:.4g} mm RMS); fix the file's units")


def noise_free(res: CalibrationResult, declared: float | None) -> str | None:
    """One line when ``res`` was fitted to noise-free data and no noise was declared, else None."""
    if declared is not None or res.sigma_m is None or not res.rank:
        return None
    if res.sigma_m >= NOISE_FREE_M:
        return None
    noise = res.noise or {}
    if any(v > 0 for v in [*(noise.get("joint") or []), *(noise.get("resolution") or [])]):
        # readings of a model with encoders are quantised: a tiny residual is that quantisation (real noise the
        # posterior carries, with shared ticks as consider errors), not an absence of noise
        return None
    return (f"noise-free data (residual {res.sigma_m:.2g} m per axis): uncertainty not estimable; declare the "
            f"instrument noise with --noise (e.g. --noise 10um) for a ± that can be signed")


def far_above_noise(res: CalibrationResult, declared: float | None) -> bool:
    """The fit is far above the noise: above the declared noise (chi-square, as the solver judges it) or, with
    none declared, above what any touch station shows."""
    rms = res.residuals.get("rms_after_m")
    if rms is None or not math.isfinite(rms):
        return False
    if declared is not None:
        return bool((res.noise or {}).get("source") == "fitted") and rms > 3.0 * declared
    return rms > FAR_ABOVE_M


def _column_hypotheses(model) -> list[tuple[int, float, str]]:
    out = []
    for j, joint in enumerate(model.joints):
        name = f"q{j + 1}"
        if joint.revolute:
            out += [(j, DEG, f"the {name} readings look like degrees under a radian header"),
                    (j, 1 / DEG, f"the {name} readings look like radians under a degree header"),
                    (j, 1e-3, f"the {name} readings are 1000× too large — mrad (mdeg) under a rad (deg) header?"),
                    (j, 1e3, f"the {name} readings are 1000× too small — rad (deg) under a mrad (mdeg) header?")]
        else:
            out += [(j, 1e-3, f"the {name} readings are 1000× too large — mm under a m header?"),
                    (j, 1e3, f"the {name} readings are 1000× too small — m under a mm header?")]
    return out


def _row_residuals(model, obs: Observations, res: CalibrationResult) -> np.ndarray | None:
    """Tool position misfit per row with the fitted model and points (touch mode only), m."""
    if obs.measured is not None:
        return None
    pts = res.points()
    try:
        tip = res.calibrated(model).fk(obs.q).reshape(-1, 4, 4)[:, :3, 3]
    except Exception:  # a model that cannot take the fitted values: no ranking, rows are tried in order
        return None
    ref = np.array([pts.get(str(lb), np.full(3, np.nan)) for lb in obs.point])
    d = np.linalg.norm(tip - ref, axis=1)
    return np.where(np.isfinite(d), d, 0.0)


SCREEN = 0.8  # a hypothesis must pull the nominal model's touches of each point this much closer to be refitted


def _spread(model, obs: Observations, q: np.ndarray) -> float | None:
    """RMS distance of the nominal model's tips from the centroid of their point's touches (touch mode): a unit
    slip scatters the poses by radians or metres, and its fix brings them back to the model's error, so a
    hypothesis that leaves this spread where it was is not worth a refit (each costs a whole solve)."""
    if obs.measured is not None:
        return None
    try:
        P = model.position(q)
    except Exception:  # noqa: BLE001 - a reading the model cannot take: no screen
        return None
    keys = [str(p) for p in obs.point] if obs.fixture is None else [f"{p}@{f}" for p, f in
                                                                   zip(obs.point, obs.fixture, strict=True)]
    arr = np.array(keys, dtype=object)
    d = []
    for k in dict.fromkeys(keys):  # np.unique of objects would import numpy.ma on the solve path
        p = P[arr == k]
        d.append(np.sum((p - p.mean(axis=0)) ** 2))
    return float(np.sqrt(np.sum(d) / len(P)))


def _gross_outliers(res: CalibrationResult) -> list[tuple[int, float]]:
    """(row, residual m) of the touches the fit excluded that are too far off for a bad touch."""
    out = []
    for o in res.outliers:
        r = o.get("residual_m")
        if isinstance(o.get("index"), int) and isinstance(r, float) and math.isfinite(r) and r > FAR_ABOVE_M:
            out.append((o["index"], r))
    return sorted(out, key=lambda t: -t[1])


def unit_slip(model, obs: Observations, res: CalibrationResult,
              refit: Callable[[Observations], CalibrationResult], declared: float | None = None,
              path: str = "samples", lines: list[int] | None = None) -> Slip | None:
    """The one unit hypothesis that explains a misfit, or None (no slip found, or the fit is fine).

    * A fit far above the noise: each column, then each of the worst rows, rescaled; a hypothesis that brings
      the RMS down ``GAIN`` times to the noise explains it.
    * A good fit that excluded rows far too off for a bad touch: each such row rescaled; a hypothesis after
      which the row fits with the rest (no longer an outlier, the RMS no worse) explains it.

    ``refit(obs)`` solves again exactly as the caller did. ``path``/``lines`` (file line of each row) name the
    place as the samples reader does (``FILE:LINE: row 7``)."""
    search = _SlipSearch(model, obs, refit, path, lines)
    rms0 = float(res.residuals.get("rms_after_m", math.inf))
    if far_above_noise(res, declared):
        return search.far_fit(res, rms0, declared)
    return search.gross_rows(res, rms0)


# a row's revolute readings rescaled: the factor and what it means
_ROW_UNITS = ((DEG, "the readings look like degrees under a radian header"),
              (1 / DEG, "the readings look like radians under a degree header"))


class _SlipSearch:
    """Tries unit hypotheses (the readings rescaled) with the caller's own solve; keeps the best that fits."""

    def __init__(self, model, obs: Observations, refit: Callable[[Observations], CalibrationResult], path: str,
                 lines: list[int] | None) -> None:
        self.model, self.obs, self.refit, self.path, self.lines = model, obs, refit, path, lines
        self.lo = np.array([j.lower for j in model.joints]) - 0.1
        self.hi = np.array([j.upper for j in model.joints]) + 0.1
        self.rot = np.array([jt.revolute for jt in model.joints])
        self.best: Slip | None = None
        self.spread0: list[float | None] = []  # computed on the first hypothesis that needs it

    def attempt(self, qn: np.ndarray, where: str, factor: float, unit: str, before: float, fits) -> None:
        if np.any(qn < self.lo) or np.any(qn > self.hi):
            return  # the rescaled readings are impossible: not this hypothesis
        if not self.spread0:
            self.spread0.append(_spread(self.model, self.obs, self.obs.q))
        if self.spread0[0] is not None and not _spread(self.model, self.obs, qn) < SCREEN * self.spread0[0]:
            return  # the nominal model's touches do not come together: no refit can explain the misfit with it
        try:
            r = self.refit(dataclasses.replace(self.obs, q=qn))
        except Exception:  # a hypothesis the solver refuses is simply not the explanation
            return
        rms = float(r.residuals.get("rms_after_m", math.inf))
        if math.isfinite(rms) and fits(r, rms) and (self.best is None or rms < self.best.rms_m):
            self.best = Slip(where, factor, unit, rms, before)

    def row_where(self, i: int) -> str:
        line = f":{self.lines[i]}" if self.lines is not None and i < len(self.lines) else ""
        return f"{self.path}{line}: row {i + 1}"

    def rescaled_row(self, i: int, factor: float) -> np.ndarray:
        qn = self.obs.q.copy()
        qn[i, self.rot] *= factor
        return qn

    def far_fit(self, res: CalibrationResult, rms0: float, declared: float | None) -> Slip | None:
        """A fit far above the noise: each column, then each of the worst rows, rescaled."""
        target = max(rms0 / GAIN, (3.0 * declared) if declared is not None else 0.0)
        if declared is None:
            target = min(target, FAR_ABOVE_M)

        def to_noise(r, rms):
            return rms <= target

        q = self.obs.q
        for j, factor, unit in _column_hypotheses(self.model):
            qn = q.copy()
            qn[:, j] *= factor
            self.attempt(qn, f"{self.path}: column q{j + 1}", factor, unit, rms0, to_noise)
        if self.best is not None:
            return self.best
        d = _row_residuals(self.model, self.obs, res)
        rows = list(range(len(q))) if d is None else [int(i) for i in np.argsort(-d, kind="stable")]
        for i in rows[:MAX_ROWS]:
            for factor, unit in _ROW_UNITS:
                self.attempt(self.rescaled_row(i, factor), self.row_where(i), factor, unit, rms0, to_noise)
        return self.best

    def gross_rows(self, res: CalibrationResult, rms0: float) -> Slip | None:
        """A good fit that excluded rows far too off for a bad touch: each such row rescaled joins the rest?"""
        for i, resid in _gross_outliers(res)[:MAX_ROWS]:
            def joins(r, rms, i=i):
                return rms <= 1.5 * rms0 and all(o.get("index") != i for o in r.outliers)

            for factor, unit in _ROW_UNITS:
                self.attempt(self.rescaled_row(i, factor), self.row_where(i), factor, unit, resid, joins)
            if self.best is not None:
                return self.best
        return self.best
