"""``CalibrationResult``: what a solve found, in SI, with per-parameter standard errors and the names and
reasons of everything the data could not identify. ``to_dict`` is the result JSON of ``station solve``."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

FORMAT = "station-calibration/1"


@dataclass
class ParameterEstimate:
    name: str
    value: float  # SI; the nominal value when not identifiable
    nominal: float
    std: float | None  # posterior std (SI); None when not identified (never a number the data did not earn)
    identifiable: bool
    reason: str = ""  # why not identifiable; empty otherwise
    kind: str = "model"  # "model" (goes into the model), "point" (reference), "instrument" (nuisance frame)
    unit: str = "m"  # "m" or "rad"
    prior_std: float | None = None  # the tolerance the estimate started from (model parameters; None: no prior)
    shrinkage: float | None = None  # 1 - std^2 / prior_std^2: how much of the prior variance the data removed
    fix: str = ""  # for a parameter not identified: what would make it identifiable
    cause: str = ""  # for a parameter not identified: a structural cause (e.g. point_rotation, scale) or "weak"
    # how much the prior contributed: its share of the estimate's information (0: the data alone, 1: the prior
    # alone, as for a parameter kept at nominal); None without a prior
    prior_share: float | None = None

    def to_dict(self) -> dict:
        return {"value": _num(self.value), "std": self.std, "identifiable": self.identifiable,
                "reason": self.reason or None, "nominal": _num(self.nominal), "kind": self.kind, "unit": self.unit,
                "prior_std": self.prior_std, "shrinkage": self.shrinkage, "prior_share": self.prior_share,
                "fix": self.fix or None, "cause": self.cause or None}

    @classmethod
    def from_dict(cls, name: str, d: dict) -> ParameterEstimate:
        return cls(name, _float(d["value"]), _float(d.get("nominal", d["value"])),
                   None if d.get("std") is None else float(d["std"]), bool(d["identifiable"]),
                   d.get("reason") or "", d.get("kind", "model"), d.get("unit", "m"),
                   None if d.get("prior_std") is None else float(d["prior_std"]),
                   None if d.get("shrinkage") is None else float(d["shrinkage"]), d.get("fix") or "",
                   d.get("cause") or "", None if d.get("prior_share") is None else float(d["prior_share"]))


def _num(v: float) -> float | None:
    """JSON has no NaN: a value the data do not determine is written as null."""
    return float(v) if v is not None and math.isfinite(v) else None


def _float(v) -> float:
    return math.nan if v is None else float(v)


@dataclass
class CalibrationResult:
    model: str
    parameters: dict[str, ParameterEstimate]
    residuals: dict[str, float | int | None]
    rank: int
    n_parameters: int
    converged: bool
    iterations: int
    condition_number: float | None = None
    observability_index: float | None = None
    sigma_m: float | None = None  # residual standard deviation sigma_hat = sqrt(|r|^2 / (m - p))
    covariance: np.ndarray | None = None  # over ``identified`` (SI)
    n_samples: int = 0
    n_residuals: int = 0
    holdout: dict | None = None
    settings: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    # trust: False when the solve did not converge, the identified set did not settle, a parameter left its
    # tolerance by more than 5 prior std (collapse/runaway), or too many touches were outliers. A result
    # that is not trusted must not PASS nor be written back; ``failure`` says why in one line.
    trusted: bool = True
    failure: str | None = None
    outliers: list[dict] = field(default_factory=list)  # {"index", "point", "residual_m", "standardised"}
    noise: dict = field(default_factory=dict)  # sigma used for the uncertainty and where it came from
    # known distances and planes: {"kind": "distance"|"plane", "labels", "fixture", "stated_m", "fitted_m",
    # "residual_m", ...} (docs/formats.md)
    constraints: list[dict] = field(default_factory=list)
    solve_time_s: float | None = None
    # prior-data conflicts: {"parameter", "data_offset" (data estimate - nominal, SI), "data_std", "prior_std", "z",
    # "freed" (estimated from the data alone) , "unit"}; a conflict the data cannot settle makes the result untrusted
    conflicts: list[dict] = field(default_factory=list)
    # why a fit that is not trusted failed, when the data show a cause (backlash, unseated touches, wrong tip link):
    # {"cause", "evidence", "action"}; see station.solver.diagnose
    diagnosis: dict | None = None

    # ---- convenience -----------------------------------------------------------------------------
    @property
    def identified(self) -> list[str]:
        return [n for n, p in self.parameters.items() if p.identifiable]

    @property
    def unidentifiable(self) -> dict[str, str]:
        return {n: p.reason for n, p in self.parameters.items() if not p.identifiable}

    def values(self, kind: str | None = "model", identified_only: bool = True) -> dict[str, float]:
        return {n: p.value for n, p in self.parameters.items()
                if (kind is None or p.kind == kind) and (p.identifiable or not identified_only)}

    def points(self) -> dict[str, np.ndarray]:
        """Reference point positions (m) that were solved or given, by label."""
        out: dict[str, list[float]] = {}
        for n, p in self.parameters.items():
            if p.kind == "point":
                _, label, axis = n.split(".", 2)
                out.setdefault(label, [math.nan] * 3)["xyz".index(axis)] = p.value
        return {k: np.array(v) for k, v in out.items()}

    def calibrated(self, model):
        """``model`` with every identified model parameter set to its estimate (points and the instrument
        frame are not part of the robot and are left out)."""
        if model.name != self.model:
            raise ValueError(f"calibration is for model {self.model!r}, not {model.name!r}")
        return model.with_params(self.values("model"))

    # ---- JSON ------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        cov = None
        if self.covariance is not None:
            cov = {"names": self.identified, "matrix": np.asarray(self.covariance).tolist()}
        return {
            "format": FORMAT,
            "units": "SI (m, rad)",
            "model": self.model,
            "parameters": {n: p.to_dict() for n, p in self.parameters.items()},
            "identified": self.identified,
            "unidentifiable": self.unidentifiable,
            "residuals": dict(self.residuals),
            "rank": self.rank,
            "n_parameters": self.n_parameters,
            "condition_number": self.condition_number,
            "observability_index": self.observability_index,
            "sigma_m": self.sigma_m,
            "converged": self.converged,
            "iterations": self.iterations,
            "n_samples": self.n_samples,
            "n_residuals": self.n_residuals,
            "holdout": self.holdout,
            "covariance": cov,
            "settings": dict(self.settings),
            "notes": list(self.notes),
            "trusted": self.trusted,
            "failure": self.failure,
            "outliers": [dict(o) for o in self.outliers],
            "noise": dict(self.noise),
            "constraints": [dict(c) for c in self.constraints],
            "conflicts": [dict(c) for c in self.conflicts],
            "diagnosis": None if self.diagnosis is None else dict(self.diagnosis),
            "solve_time_s": self.solve_time_s,
        }

    @classmethod
    def from_dict(cls, d: dict) -> CalibrationResult:
        try:
            params = {n: ParameterEstimate.from_dict(n, v) for n, v in d["parameters"].items()}
            cov = d.get("covariance")
            return cls(
                model=str(d["model"]), parameters=params, residuals=dict(d["residuals"]), rank=int(d["rank"]),
                n_parameters=int(d["n_parameters"]), converged=bool(d["converged"]),
                iterations=int(d["iterations"]), condition_number=d.get("condition_number"),
                observability_index=d.get("observability_index"), sigma_m=d.get("sigma_m"),
                covariance=None if not cov else np.array(cov["matrix"], dtype=float),
                n_samples=int(d.get("n_samples", 0)), n_residuals=int(d.get("n_residuals", 0)),
                holdout=d.get("holdout"), settings=dict(d.get("settings", {})), notes=list(d.get("notes", [])),
                trusted=bool(d.get("trusted", d["converged"])), failure=d.get("failure"),
                outliers=list(d.get("outliers") or []), noise=dict(d.get("noise") or {}),
                constraints=list(d.get("constraints") or []),
                solve_time_s=d.get("solve_time_s"), conflicts=list(d.get("conflicts") or []),
                diagnosis=None if not d.get("diagnosis") else dict(d["diagnosis"]))
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"not a calibration result: {type(e).__name__}: {e}") from None
