"""Compensated targets for a controller that keeps its own (nominal) kinematics.

The controller turns a target into joint values with its nominal model; the robot, as the calibration knows it,
puts the tool elsewhere. Given targets in the base frame, the compensation is the inverse kinematics of the
CALIBRATED model: those joint values put the calibrated model's tool on the target. A controller that takes
joint moves gets them as they are; one that takes Cartesian moves gets the pose its nominal model assigns to
them (``FK_nominal(q)``): its own inverse kinematics brings back the same joint values, in the same
configuration. Per target: the predicted residual (what the calibrated model still leaves: the inverse
kinematics' own error, e.g. an orientation a 4-axis arm cannot take), its uncertainty from the calibration's
covariance (the tool pose's standard deviation through the parameter Jacobian), and the error the uncompensated
target would have had (the correction). Pure: arrays in and out, SI."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from station.kinematics import se3

IK_TOL = 1e-9  # m / rad: a target is reached when the inverse kinematics is this close
SEEDS = 24  # random joint seeds (within the limits) for a first target without a start configuration
FLIP = 1.0  # rad: compensated joints this far from the nominal ones are another configuration, not a correction


@dataclass
class Compensation:
    q: np.ndarray  # (N, n) compensated joint commands (nan: not reached)
    q_nominal: np.ndarray  # (N, n) what the controller would command for the raw target
    status: list[str]  # "ok" or why not
    cartesian: np.ndarray  # (N, 6) the corrected Cartesian target for a controller with the nominal model
    residual: np.ndarray  # (N,) m: position error the calibrated model predicts for the command
    residual_rotation: np.ndarray  # (N,) rad
    sigma: np.ndarray  # (N,) m: 3-D RMS of the predicted position (sqrt of the covariance's trace)
    sigma_rotation: np.ndarray  # (N,) rad
    correction: np.ndarray  # (N,) m: the position error the uncompensated target would leave (calibrated model)

    @property
    def ok(self) -> np.ndarray:
        return np.array([s == "ok" for s in self.status])


def _targets(targets) -> tuple[np.ndarray, bool]:
    """``(N, 4, 4)`` poses (orientation from rotation vectors when given) and whether orientation counts."""
    t = np.atleast_2d(np.asarray(targets, float))
    if t.ndim == 3:
        return t, True
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, :3, 3] = t[:, :3]
    if t.shape[1] == 6:
        T[:, :3, :3] = se3.rotvec_to_matrix(t[:, 3:])
        return T, True
    return T, False


def _ik(model, T: np.ndarray, seed: np.ndarray, full: bool):
    res = model.ik(T if full else T[:, :3, 3], seed, position_only=not full, tol_pos=IK_TOL, tol_rot=IK_TOL,
                   max_iter=300)
    good = (res.position_error < 1e-7) & (res.orientation_error < 1e-7 if full else True)
    return res.q, good & res.ok


def _first_seed(model, T: np.ndarray, full: bool, start) -> np.ndarray | None:
    """A start configuration for the first target: the given one, else the reachable solution nearest the middle of
    the joint ranges from a spread of seeds (seeded: the same targets give the same commands)."""
    if start is not None:
        return np.asarray(start, float)
    lo, hi = model.lower, model.upper
    mid = (lo + hi) / 2
    rng = np.random.default_rng(0)
    seeds = np.vstack([mid, np.zeros(model.n_joints).clip(lo, hi), rng.uniform(lo, hi, (SEEDS, model.n_joints))])
    q, good = _ik(model, np.repeat(T[None], len(seeds), axis=0), seeds, full)
    if not good.any():
        return None
    cand = q[good]
    return cand[np.argmin(np.linalg.norm((cand - mid) / (hi - lo), axis=1))]


ABSORBED = ("redundant", "tool_free")  # causes of a parameter kept at nominal whose effect identified ones take up


def pose_covariance(model, q: np.ndarray, covariance, names: list[str], kept: dict | None = None) -> np.ndarray:
    """``(N, 6, 6)`` covariance of the tool pose (position, then rotation about the base axes) at joint values
    ``q``, from the calibration's covariance of the identified parameters ``names`` (those of the model; the
    instrument frame and reference points are not the robot's).

    The solver's covariance is a "consider" covariance: a parameter kept at nominal adds its prior variance to the
    identified ones it moves (docs/solver.md). ``kept`` (``{name: (prior std, cause)}``) says what each kept one
    does at the tool: one with the same effect as identified ones at every pose (``ABSORBED`` causes) is taken up
    by them exactly, so its share is removed; one the data saw too weakly (any other cause) is an error the
    calibrated model keeps, so its own effect at the tool is added."""
    q = np.atleast_2d(q)
    out = np.zeros((len(q), 6, 6))
    if covariance is None or not len(names):
        return out
    cov = np.asarray(covariance, float)
    keep = [i for i, n in enumerate(names) if n in model.param_names]
    if not keep:
        return out
    cols = [model.index(names[i]) for i in keep]
    C = cov[np.ix_(keep, keep)]
    _, _, Jp = model.jacobians(q)
    J = Jp[:, :, cols]
    out = J @ C @ np.swapaxes(J, 1, 2)
    for name, (std, cause) in (kept or {}).items():
        if name not in model.param_names or not std:
            continue
        jk = Jp[:, :, model.index(name)][:, :, None]
        share = float(std) ** 2 * (jk @ np.swapaxes(jk, 1, 2))
        out = out - share if cause in ABSORBED else out + share
    w, V = np.linalg.eigh(out)  # the removal is exact only to rounding: no negative variance
    return (V * np.maximum(w, 0.0)[:, None, :]) @ np.swapaxes(V, 1, 2)


@dataclass
class Design:
    """What the calibration was solved from, enough to weigh its parameters again: the joint readings ``q`` of
    its samples, their point labels, whether an instrument measured them (in its own frame, solved as a
    nuisance, unless ``frame_known``), the noise per axis it fitted (m) and the prior std of every model
    parameter it considered (identified or kept at nominal)."""

    q: np.ndarray
    labels: np.ndarray
    measured: bool
    frame_known: bool
    sigma: float
    priors: dict[str, float]
    known_points: tuple[str, ...] = ()


def predictive_covariance(model, design: Design) -> tuple[np.ndarray, list[str]]:
    """The posterior covariance of the model parameters the calibration considered, from its own samples
    (linearised at the calibrated model): ``H = B^T B / sigma^2 + diag(1/prior^2)`` over the parameters and the
    nuisances (the instrument frame, or the unknown reference points), inverted, the parameters' block kept.
    Unlike the solver's reported covariance (a "consider" covariance: each parameter kept at nominal adds its
    whole prior to the ones it moves), a tool pose predicted from it sees an aliased pair (a TCP offset and the
    last link's length) as the one combination the data fixed: the honest uncertainty of a compensated pose."""
    names = [n for n in design.priors if n in model.param_names]
    q = np.atleast_2d(design.q)
    T, _, Jp = model.jacobians(q)
    p = T[:, :3, 3]
    blocks = [Jp[:, :3, [model.index(n) for n in names]]]  # (N, 3, P)
    N = len(q)
    if design.measured and not design.frame_known:  # the instrument frame: a small motion of every reading
        skew = np.zeros((N, 3, 3))
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -p[:, 2], p[:, 1], -p[:, 0]
        skew = skew - np.swapaxes(skew, 1, 2)
        blocks.append(np.concatenate([np.tile(np.eye(3), (N, 1, 1)), skew], axis=2))
    elif not design.measured:  # unknown reference points: each label's position
        labels = [lb for lb in dict.fromkeys(design.labels) if lb not in design.known_points]
        cols = np.zeros((N, 3, 3 * len(labels)))
        for k, lb in enumerate(labels):
            cols[design.labels == lb, :, 3 * k:3 * k + 3] = -np.eye(3)
        blocks.append(cols)
    B = np.concatenate(blocks, axis=2).reshape(3 * N, -1)
    prior = np.zeros(B.shape[1])
    prior[:len(names)] = [1.0 / design.priors[n] ** 2 for n in names]
    H = B.T @ B / max(design.sigma, 1e-12) ** 2 + np.diag(prior)
    cov = np.linalg.pinv(H, hermitian=True)
    return cov[:len(names), :len(names)], names


def compensate(nominal, calibrated, targets, *, covariance=None, names: list[str] | None = None,
               kept: dict | None = None, start=None) -> Compensation:
    """Joint commands that put the calibrated model's tool on ``targets`` (``(N, 3)`` positions, ``(N, 6)`` with
    rotation vectors or ``(N, 4, 4)``; base frame), each row seeded from the previous one (a path stays in one
    configuration), the first from ``start`` or a spread of seeds."""
    T, oriented = _targets(targets)
    n = nominal.n_joints
    full = oriented and n >= 6
    N = len(T)
    q_cal = np.full((N, n), np.nan)
    q_nom = np.full((N, n), np.nan)
    status = ["ok"] * N
    prev = None
    for i in range(N):
        seed = prev if prev is not None else _first_seed(nominal, T[i], full, start)
        if seed is None:
            status[i] = "unreachable: no configuration of the nominal model reaches the target"
            continue
        qn, gn = _ik(nominal, T[i:i + 1], seed[None], full)
        qc, gc = _ik(calibrated, T[i:i + 1], (qn if gn[0] else seed[None]), full)
        if gn[0]:
            q_nom[i] = qn[0]
        if not gc[0]:
            status[i] = "unreachable: the calibrated model cannot reach it within the joint limits"
            continue
        if gn[0] and np.max(np.abs(qc[0] - qn[0])) > FLIP:
            status[i] = "unreachable: only in another configuration than the nominal command's"
            continue
        q_cal[i] = qc[0]
        prev = qc[0]
    ok = np.array([s == "ok" for s in status])
    cart = np.full((N, 6), np.nan)
    res_p, res_r = np.full(N, np.nan), np.full(N, np.nan)
    sig_p, sig_r, corr = np.full(N, np.nan), np.full(N, np.nan), np.full(N, np.nan)
    if ok.any():
        Tc = calibrated.fk(q_cal[ok]).reshape(-1, 4, 4)
        res_p[ok] = np.linalg.norm(Tc[:, :3, 3] - T[ok, :3, 3], axis=1)
        res_r[ok] = np.linalg.norm(se3.orientation_error(T[ok, :3, :3], Tc[:, :3, :3]), axis=1) if oriented else 0.0
        cart[ok] = se3.matrix_to_pose(nominal.fk(q_cal[ok]).reshape(-1, 4, 4), "rotvec")
        S = pose_covariance(calibrated, q_cal[ok], covariance, names or [], kept)
        sig_p[ok] = np.sqrt(np.trace(S[:, :3, :3], axis1=1, axis2=2))
        sig_r[ok] = np.sqrt(np.trace(S[:, 3:, 3:], axis1=1, axis2=2))
    has_nom = ~np.isnan(q_nom).any(axis=1)
    if has_nom.any():
        Tn = calibrated.fk(q_nom[has_nom]).reshape(-1, 4, 4)
        corr[has_nom] = np.linalg.norm(Tn[:, :3, 3] - T[has_nom, :3, 3], axis=1)
    return Compensation(q_cal, q_nom, status, cart, res_p, res_r, sig_p, sig_r, corr)


def urscript(q: np.ndarray, status: list[str], *, name: str = "station_compensated", a: float = 1.2,
             v: float = 0.25, header: str = "") -> str:
    """A URScript program with one ``movej`` per reached target (joint values in rad), in order; an unreached
    target is a comment line, never a move."""
    lines = [f"def {name}():"]
    lines += [f"  # {h}" for h in header.splitlines() if h]
    for i, (row, st) in enumerate(zip(q, status, strict=True)):
        if st != "ok":
            lines.append(f"  # target {i + 1}: not moved ({st})")
            continue
        lines.append(f"  movej([{', '.join(f'{v_:.9f}' for v_ in row)}], a={a:g}, v={v:g})  # target {i + 1}")
    lines.append("end")
    return "\n".join(lines) + "\n"
