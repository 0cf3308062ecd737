"""The plan-time check: the posterior standard deviation of every parameter from PLANNED poses and a declared
touch noise, before anything moves.

The planned joint values put the NOMINAL tool on the points (the robot will be near them); the prediction is the
same statistics the solver reports afterwards (``docs/solver.md``), evaluated at the nominal model: the
structural analysis (what the poses cannot see at all, and why), the identified set (posterior std at most
``MAX_RATIO`` of the prior and ``max_std`` at the tool) and the consider covariance (what stays at nominal
contributes its prior variance). Noise-free, so it needs no data: only poses, labels, reference and noise.
The jog UI's "good enough" indicator and ``station run``'s refusal before motion use ``predict(...).ok``."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from station.solver.estimator import _prior_vector, select_names
from station.solver.identifiability import priority_order, structure
from station.solver.observations import Observations, SolverInputError
from station.solver.posterior import decide, posterior
from station.solver.problem import Problem


@dataclass
class ParameterPrediction:
    name: str
    std: float | None  # predicted posterior std (SI, consider covariance); None: not identifiable (at nominal)
    prior_std: float
    identifiable: bool
    reason: str = ""  # why not (structural cause, or "poorly observed")
    fix: str = ""  # what would make it identifiable


@dataclass
class Prediction:
    parameters: dict[str, ParameterPrediction] = field(default_factory=dict)
    noise_m: float = 0.0

    @property
    def missing(self) -> dict[str, str]:
        """Requested model parameters the plan cannot identify -> reason (and fix)."""
        return {n: (p.reason + (f"; {p.fix}" if p.fix else "")) for n, p in self.parameters.items()
                if not p.identifiable}

    @property
    def ok(self) -> bool:
        """Good enough: every requested model parameter is predicted to be identified."""
        return not self.missing


def predict(model, q, points, identify="offsets,tcp", reference="unknown", *, noise: float,
            priors=None, max_std: float | None = None) -> Prediction:
    """Predicted posterior std per requested model parameter for touches at joint values ``q`` (N, n) of
    points ``points`` (N labels), with ``reference`` as for ``solve`` (``"unknown"`` or ``{label: xyz}``)
    and the declared touch noise ``noise`` (m per axis). Raises SolverInputError for bad input."""
    if not (isinstance(noise, (int, float)) and math.isfinite(noise) and noise > 0):
        raise SolverInputError(f"noise must be a positive number of metres, got {noise!r}")
    obs = Observations(np.asarray(q, dtype=float), np.asarray(points, dtype=object))
    prob = Problem(model, obs, select_names(model, identify), reference)
    if 3 * len(obs) <= prob.n_unknowns:
        raise SolverInputError(f"{len(obs)} planned touches give {3 * len(obs)} equations for {prob.n_unknowns} "
                               "unknowns")
    x = prob.initial()
    struct = structure(prob, x, None)
    _, J = prob.residual_jacobian(x, q=prob.consistent_q(x, 2))
    BtB = J.T @ J
    prior = _prior_vector(prob, priors)
    tool = prob.tool_per_unit()
    order = priority_order(prob.names, prob.kinds)
    dec = decide(BtB, sorted(struct.accepted), order, [], noise, prior, tool, max_std, 1.0)
    A = dec.accepted
    kept = [j for j in range(prob.n_unknowns) if j not in A]
    post = posterior(BtB, A, kept, noise, prior) if A else None
    out = Prediction(noise_m=float(noise))
    for j, n in enumerate(prob.names):
        if prob.kinds[j] != "model":
            continue
        if j in A:
            out.parameters[n] = ParameterPrediction(n, float(post.std[A.index(j)]), float(prior[j]), True)
        elif j in struct.nulls:
            nl = struct.nulls[j]
            out.parameters[n] = ParameterPrediction(n, None, float(prior[j]), False, nl.reason, nl.fix)
        else:
            would, pr = dec.weak.get(j, (math.nan, float(prior[j])))
            out.parameters[n] = ParameterPrediction(
                n, None, float(prior[j]), False,
                f"poorly observed: the plan would leave its std at {would / pr:.0%} of its prior",
                "more touches, a wider pose spread, or lower noise")
    return out
