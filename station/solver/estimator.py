"""``solve``: iterated Gauss-Newton / Levenberg-Marquardt on the analytic Jacobian with identifiability
analysis and covariance. Seed 000's linear solve ``phi = (B^T B)^-1 B^T Y`` is the first Gauss-Newton
step; seed 002's loop ``dphi = (J^T J)^-1 J^T e`` until ``|dphi| < eps`` is this loop without damping."""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg.lapack import dpotrf, dtrtri

from station.solver.identifiability import RTOL, Decision, RankAnalysis, analyse, decide
from station.solver.observations import Observations, SolverInputError
from station.solver.problem import Problem
from station.solver.result import CalibrationResult, ParameterEstimate

XTOL = 1e-11  # m (scaled step): below this a step changes nothing measurable
FTOL = 1e-13  # relative cost decrease
STEP_TOL = 1e-4  # standard deviations: what is left of the way to the minimum when the iteration stops
DECIDE_TOL = 0.1  # standard deviations: close enough to the minimum to decide identifiability with its sigma
DECIDE_MARGIN = 2.0  # remainders this far (factor) from the threshold: a decision that re-solving cannot flip
POSE_TOL = 1e-3  # rad or m: joint readings closer than this are the same pose


def select_names(model, identify) -> list[str]:
    """Model parameter names of ``identify`` (groups, names, globs); the ``points`` group is implicit."""
    spec = identify.split(",") if isinstance(identify, str) else list(identify)
    spec = [t for t in (s.strip() for s in spec) if t and t != "points"]
    if not spec:
        return []
    try:
        return model.select(spec)
    except KeyError as e:
        raise SolverInputError(str(e.args[0])) from None


def solve(model, obs: Observations, identify="offsets,tcp", reference="unknown", holdout: Observations | None = None,
          *, instrument_frame: str = "unknown", noise: float | None = None, max_std: float = 1e-3,
          max_iter: int = 100) -> CalibrationResult:
    """Identify ``identify`` of ``model`` from touch observations.

    ``reference``: ``"unknown"`` (every touched point is a nuisance unknown ``point.LABEL.{x,y,z}``) or
    ``{label: xyz}`` known positions in the robot base frame (m); labels not given are solved as unknown.
    With instrument measurements (``obs.measured``) the reference labels are not used; the instrument
    frame is solved as the nuisance ``base.*`` (``instrument_frame="unknown"``) or the measurements are
    taken as base-frame positions (``"base"``). ``noise`` (m): touch noise for the rank decision; default:
    the residual standard deviation of the fit. ``max_std`` (m at the tool): weaker directions are named
    unidentifiable instead of estimated."""
    if not isinstance(obs, Observations):
        raise SolverInputError("obs must be an Observations")
    if getattr(model, "kind", "serial") == "parallel":  # station/kinematics/parallel.py
        raise SolverInputError(f"model {model.name} is a parallel robot: parametric identification needs a serial "
                               f"chain; calibrate it with 'station map' (docs/map.md)")
    if obs.q.shape[1] != model.n_joints:
        raise SolverInputError(f"model {model.name} has {model.n_joints} joints, observations have {obs.q.shape[1]}")
    if instrument_frame not in ("unknown", "base"):
        raise SolverInputError(f"instrument_frame must be 'unknown' or 'base', got {instrument_frame!r}")
    names = select_names(model, identify)
    prob = Problem(model, obs, names, reference, instrument_frame)
    m, p = 3 * len(obs), prob.n_unknowns
    if m <= p:
        raise SolverInputError(
            f"{len(obs)} samples give {m} equations for {p} unknowns ({len(names)} model parameters"
            f"{', instrument frame' if prob.frame_unknown else ''}, {len(prob.unknown_points)} unknown point(s)); "
            f"need at least {p // 3 + 1} samples, ~20 well spread poses recommended")
    k = distinct_poses(obs.q, limit=p // 3 + 1)
    if 3 * k <= p:
        raise SolverInputError(
            f"only {k} distinct pose(s) among {len(obs)} samples (readings within {POSE_TOL * 1e3:g} mrad/um count as "
            f"one): {3 * k} equations for {p} unknowns; move the robot between touches")
    x, r, J = prob.initial_with_jacobian(scaled=True)  # J column-scaled throughout (angles times L)
    x_start = x.copy()
    r_before = r
    dec = _decide(prob, J, x, noise or 0.0, max_std, r)
    # Iterate on what is structurally identifiable, then decide with the fit's sigma (dependencies like
    # "offset.j1 vs an unknown point" are exact only where the touches are consistent, i.e. at the
    # solution; a sigma from an unconverged fit would reject good parameters). The decision only needs
    # the fit within DECIDE_TOL standard deviations of the minimum (sigma is then within ~1e-3 of its
    # final value); once the identified set stands, the iteration finishes to STEP_TOL on that set.
    iterations, converged, current = 0, False, False
    tol, prev, exact, settled, finishing = DECIDE_TOL, None, True, False, False
    for _ in range(8):
        act = sorted(dec.accepted)
        if not exact:  # the last step was taken on the linear model: evaluate the chain there first
            r, J = prob.residual_jacobian(x, scaled=True)
        x, r, J, it, converged, rest, exact, prev, (xe, re) = _levenberg_marquardt(prob, x, act, max_iter, (r, J),
                                                                                  tol, prev)
        iterations += it
        if finishing:  # finished on a set decided within DECIDE_TOL of this minimum
            break
        if settled:
            # the last decision dropped columns with every remainder at least DECIDE_MARGIN away from the
            # threshold: re-solving without them moves sigma and the Jacobian far less than that
            current = True
        else:
            sig = noise if noise is not None else math.sqrt(float(r @ r) / (m - len(act)))
            dec = _decide(prob, J, x, sig, max_std, r)
            current = sorted(dec.accepted) == act
        if current and (rest < STEP_TOL or not converged):
            break
        if current:
            tol, finishing = STEP_TOL, True
            continue
        settled = dec.margin >= DECIDE_MARGIN and all(j in act for j in dec.accepted)
        dropped = [j for j in act if j not in dec.accepted]
        # back to nominal: never keep numbers for an unseen direction
        if len(dropped) == 1 and dropped[0] == prob.first_joint_offset_column():
            first = dropped[0]
            # only the first joint's offset (e.g. with an unknown point): from the last evaluated point
            # that is a rigid motion of the tool positions and model columns, no chain pass needed
            x = xe.copy()
            r, J = prob.shift_first_joint(xe, re, J, x_start[first] - xe[first], first)
            x[first] = x_start[first]
        else:
            x[dropped] = x_start[dropped]
            r, J = prob.residual_jacobian(x, scaled=True)
        tol, prev, exact = DECIDE_TOL, None, True
    sig = noise if noise is not None else math.sqrt(float(r @ r) / (m - len(dec.accepted)))
    # the reasons, condition number and observability index once, at the final Jacobian
    ana = _analyse(prob, J, x, sig, max_std, r, dec if current else None)
    if not current:  # the identified set never settled within the rounds: not a minimum of the final set
        converged = False
    return _result(model, prob, x, r, J, r_before, ana, iterations, converged, holdout,
                   dict(identify=identify if isinstance(identify, str) else ",".join(identify),
                        reference=_ref_setting(reference), instrument_frame=instrument_frame,
                        noise_m=noise, max_std_m=max_std, rtol=RTOL, characteristic_length_m=prob.length,
                        max_iter=max_iter, estimator="Levenberg-Marquardt on analytic Jacobian"))


def distinct_poses(q: np.ndarray, tol: float | None = None, limit: int | None = None) -> int:
    """Number of joint configurations that differ by more than ``tol`` in some joint (greedy clustering;
    counting stops at ``limit``): repeating one pose adds no information about the geometry."""
    tol = POSE_TOL if tol is None else tol
    k = min(len(q), limit or len(q))
    if k <= 64:  # usually the first rows already differ pairwise: one vectorised check
        head = q[:k]
        d = np.max(np.abs(head[:, None] - head[None]), axis=2)
        d.flat[:: k + 1] = np.inf  # a pose is not a repeat of itself
        if d.min() > tol:
            return k
    reps = np.empty((min(len(q), limit or len(q)), q.shape[1]))
    k = 0
    for row in q:
        if not k or np.min(np.max(np.abs(reps[:k] - row), axis=1)) > tol:
            reps[k] = row
            k += 1
            if k == len(reps):
                break
    return k


def _decide(prob: Problem, J, x, sigma, max_std, r) -> Decision:
    return decide(J, prob.names, prob.kinds, sigma=sigma, max_std=max_std,
                  scale_dir=prob.scale_direction(x) / prob.scale, residual=r)


def _analyse(prob: Problem, J, x, sigma, max_std, r, decided: Decision | None = None) -> RankAnalysis:
    Js = J
    sd = prob.scale_direction(x) / prob.scale
    joints = prob.model.joints
    return analyse(Js, prob.names, prob.kinds, sigma=sigma, max_std=max_std, scale_dir=sd, residual=r,
                   n_joints=len(joints), first_revolute=joints[0].revolute, last_revolute=joints[-1].revolute,
                   decided=decided)


def _levenberg_marquardt(prob: Problem, x, act, max_iter, rJ, tol: float = STEP_TOL, prev: float | None = None):
    """Undamped Gauss-Newton steps while they reduce the cost; Marquardt damping otherwise. Stops when the
    rest of the way to the minimum is below ``tol`` standard deviations of the parameters. Gauss-Newton
    converges linearly near the minimum with rate rho (faster while the error is large compared with the
    residual), so after a step of ``s`` standard deviations at most ``s rho / (1 - rho)`` is left; rho is
    estimated by the ratio of the last two undamped steps (``prev``: the one before this call), which
    over-estimates it. A final step that small is taken without evaluating the chain again: over it the
    model is linear to O(step^2), and the residual is the linear prediction. Also stops below XTOL or
    when the cost stops decreasing.

    Returns ``x, r, J, iterations, converged, rest, exact, prev, (xe, re)``: ``rest`` is the estimate of
    what is left (standard deviations), ``exact`` whether ``r, J`` were evaluated at ``x`` (else ``r`` is
    the linear prediction and ``J`` the Jacobian one step back), ``prev`` the last undamped step, ``xe,
    re`` the point where ``J`` was evaluated and the residual there."""
    x = x.copy()
    r, J = rJ
    if not act:
        return x, r, J, 0, True, 0.0, True, None, (x, r)
    D = prob.scale[act]
    every = len(act) == J.shape[1]  # act is sorted: all columns, no selection copy
    cost = float(r @ r)
    dof = max(r.size - len(act), 1)
    eye = np.eye(len(act))
    lam = 0.0
    for it in range(1, max_iter + 1):
        Js = J if every else J[:, act]
        # normal equations on the column-scaled, full-rank (after the rank analysis) Jacobian: cond(J)^2
        # stays far from 1/eps, and any error in a step is corrected by the next iteration
        H = Js.T @ Js
        g = Js.T @ r
        Ri = _inverse_cholesky(H + lam * eye if lam else H)
        if Ri is not None:
            du = -(Ri @ (Ri.T @ g))
            rel = math.sqrt(float(np.max(du * du / (Ri * Ri).sum(axis=1))) * dof / cost) if cost else 0.0
        else:
            du = -np.linalg.lstsq(H + lam * eye, g, rcond=None)[0]
            rel = math.inf
        x_new = x.copy()
        x_new[act] += D * du
        step = float(np.max(np.abs(du)))
        if lam == 0.0:
            rho = rel / prev if prev else 1.0
            rest = rel * rho / (1.0 - rho) if rho < 0.5 else rel
            if step < XTOL:
                rest = 0.0
            if rest < tol:
                return x_new, r + Js @ du, J, it, True, rest, False, rel, (x, r)
        r_new, J_new = prob.residual_jacobian(x_new, scaled=True)
        cost_new = float(r_new @ r_new)
        if cost_new <= cost:
            small = cost - cost_new <= FTOL * cost
            prev = rel if lam == 0.0 else None
            x, r, J, cost = x_new, r_new, J_new, cost_new
            if lam:
                lam = 0.0 if lam < 1e-9 * float(np.max(np.diag(H))) else lam / 10.0
            if small:
                return x, r, J, it, True, 0.0, True, prev, (x, r)
        else:
            prev = None
            if step < XTOL:
                return x, r, J, it, True, 0.0, True, prev, (x, r)  # at the minimum within rounding
            lam = max(lam * 10.0, 1e-6 * float(np.max(np.diag(H))))
    return x, r, J, max_iter, False, math.inf, True, prev, (x, r)


def _inverse_cholesky(H: np.ndarray) -> np.ndarray | None:
    """``R^-1`` (upper triangular) with ``H = R^T R``, so ``H^-1 = R^-1 R^-T``; None when ``H`` is not
    numerically positive definite. LAPACK directly: these are small matrices, called every iteration."""
    R, info = dpotrf(H, lower=0, clean=1)
    if info != 0:
        return None
    Ri, info = dtrtri(R, lower=0)
    return Ri if info == 0 else None


def _ref_setting(reference):
    if isinstance(reference, str):
        return reference
    return {k: np.asarray(v, dtype=float).tolist() for k, v in dict(reference).items()}


def _stats(r: np.ndarray) -> tuple[float, float]:
    r = r.reshape(-1, 3)
    d = np.sqrt(np.einsum("ij,ij->i", r, r))
    return float(np.sqrt(np.mean(d**2))), float(d.max())


def _result(model, prob: Problem, x, r, J, r_before, ana: RankAnalysis, iterations, converged, holdout,
            settings) -> CalibrationResult:
    act = ana.accepted
    m = r.size
    dof = m - len(act)
    sigma = math.sqrt(float(r @ r) / dof)
    cov = None
    std = np.full(prob.n_unknowns, np.nan)
    if act:
        H = ana.gram if ana.gram is not None and ana.gram.shape[0] == len(act) else J[:, act].T @ J[:, act]
        Ri = _inverse_cholesky(H)
        cov_u = (Ri @ Ri.T if Ri is not None else np.linalg.pinv(H)) * sigma**2
        cov = cov_u * np.outer(prob.scale[act], prob.scale[act])
        std[act] = np.sqrt(np.diag(cov))
    params: dict[str, ParameterEstimate] = {}
    for i, n in enumerate(prob.names):
        kind, unit = prob.kinds[i], prob.units[i]
        nominal = float(prob.x_nominal[i]) if kind != "point" else math.nan
        if i in act:
            params[n] = ParameterEstimate(n, float(x[i]), nominal, float(std[i]), True, "", kind, unit)
        else:
            value = nominal if kind == "model" else math.nan
            params[n] = ParameterEstimate(n, value, nominal, None, False, ana.rejected[i], kind, unit)
    rms0, max0 = _stats(r_before)
    rms1, max1 = _stats(r)
    notes = []
    if not converged:
        notes.append("the iteration did not converge within max_iter; the estimate is not reliable")
    if isinstance(settings["reference"], dict):
        extra = [lb for lb in prob.unknown_points]
        if extra:
            notes.append(f"reference point(s) {', '.join(extra)} not given: solved as unknown")
    res = CalibrationResult(
        model=model.name, parameters=params,
        residuals={"rms_before_m": rms0, "max_before_m": max0, "rms_after_m": rms1, "max_after_m": max1},
        rank=ana.rank, n_parameters=prob.n_unknowns, converged=converged, iterations=iterations,
        condition_number=ana.condition_number, observability_index=ana.observability_index, sigma_m=sigma,
        covariance=cov, n_samples=len(prob.obs), n_residuals=m, settings=settings, notes=notes)
    if holdout is not None:
        res.holdout = _holdout(prob, x, act, holdout)
    return res


def _holdout(prob: Problem, x, act, ho: Observations) -> dict:
    model = prob.model
    if ho.q.shape[1] != model.n_joints:
        raise SolverInputError(f"holdout: model {model.name} has {model.n_joints} joints, got {ho.q.shape[1]}")
    xa = prob.x_nominal.copy()
    xa[act] = x[act]
    if prob.frame_unknown:  # the instrument frame is always needed to compare, identified or not
        inst = [i for i, k in enumerate(prob.kinds) if k == "instrument"]
        xa[inst] = x[inst]
    P = model.position(ho.q, prob.full_params(xa))
    if prob.instrument:
        if ho.measured is None:
            raise SolverInputError("holdout: the fit used instrument measurements; holdout needs them too")
        tgt = ho.measured
    else:
        pts = prob.points_of(x)
        missing = [lb for lb in ho.labels if lb not in pts]
        if missing:
            raise SolverInputError(f"holdout: point {missing[0]!r} was not touched in the fit and is not known")
        tgt = np.array([pts[lb] for lb in ho.point])
    rms, mx = _stats(P - tgt)
    P0 = model.position(ho.q)
    rms0, _ = _stats(P0 - tgt)
    return {"n_samples": len(ho), "rms_m": rms, "max_m": mx, "rms_nominal_m": rms0}
