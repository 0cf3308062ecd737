"""``solve``: maximum a-posteriori Gauss-Newton / Levenberg-Marquardt on the analytic Jacobian, with
priors, a structural identifiability analysis, a noise-aware decision of what the data identify,
outlier rejection, the posterior ("consider") covariance and the refusal of what cannot be trusted.

Seed 000's linear solve ``phi = (B^T B)^-1 B^T Y`` is the first Gauss-Newton step without prior; seed
002's loop ``dphi = (J^T J)^-1 J^T e`` until ``|dphi| < eps`` is this loop without damping and prior.

The loop (docs/solver.md section 3):
  1. structure: which unknowns perfect touches at these poses could identify (``identifiability``);
  2. fit every structurally identifiable unknown (MAP: the prior keeps weak directions sane);
  3. noise sigma from the FITTED residual (or the declared noise), decide which parameters the data
     shrink well below their prior (``posterior.decide``); the others return to nominal;
  4. refit and re-decide until the identified set and sigma settle; then drop touches whose
     standardised residual exceeds 4 and repeat; check the structure again at the solution."""

from __future__ import annotations

import math
import time

import numpy as np

from station.solver import holdout as holdout_mod
from station.solver.identifiability import RTOL, Null, Structure, priority_order, structure
from station.solver.noise import NoiseModel, joint_noise_of, quantisation, resolution_of
from station.solver.observations import Observations, SolverInputError
from station.solver.posterior import MAX_RATIO, decide, posterior, t_factor
from station.solver.priors import prior_stds
from station.solver.problem import Problem, angle_params, human_unit
from station.solver.result import CalibrationResult, ParameterEstimate

XTOL = 1e-12  # m or rad: below this a step changes nothing measurable
FTOL = 1e-13  # relative cost decrease
STEP_TOL = 1e-4  # standard deviations: the last step of a fit is smaller than this
SIGMA_TOL = 0.05  # relative change of sigma between fits below which the prior weights stand
MAX_ROUNDS = 12  # decide / refit rounds before "the identified set did not settle"
POSE_TOL = 1e-3  # rad or m: joint readings closer than this are the same pose
RUNAWAY = 5.0  # prior standard deviations from nominal: beyond this a result is not trusted
CONFLICT_Z = 5.0  # |data estimate - nominal| / sqrt(data var + prior var) beyond this: the prior contradicts the data
DETERMINED_M = 1e-3  # m at the tool: a parameter whose data std is within this (or max_std) is determined by the data
OUTLIER_THRESHOLD = 4.0  # standardised residual (any axis) above which a touch is excluded
MAX_OUTLIER_FRACTION = 0.2  # more outliers than this: the model does not fit the data
LOSSES = ("linear", "huber", "soft_l1")
SIGMA_FIRST = 1e-6  # m: the prior weight of the first fit when no noise is declared (see _Estimation.run)


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
          *, instrument_frame: str = "unknown", noise: float | None = None, priors=None,
          max_std: float | None = None, loss: str = "linear", outlier_threshold: float | None = OUTLIER_THRESHOLD,
          distances=None, planes=None, joint_noise=None, max_iter: int = 100,
          touch: str = "socket") -> CalibrationResult:
    """Identify ``identify`` of ``model`` from touch observations (MAP estimate with priors).

    ``reference``: ``"unknown"`` (every touched point is a nuisance unknown ``point.LABEL.{x,y,z}``) or
    ``{label: xyz}`` known positions in the robot base frame (m); labels not given are solved as unknown.
    With instrument measurements (``obs.measured``) the reference labels are not used; the instrument
    frame is solved as the nuisance ``base.*`` (``instrument_frame="unknown"``) or the measurements are
    taken as base-frame positions (``"base"``).

    ``noise`` (m, per axis): the declared touch noise; default: the residual standard deviation of the
    fitted model. ``priors``: prior standard deviations overriding the defaults and the model file's
    ``tolerances`` - ``{selector: std_SI}`` or ``[(selector, std_SI, "length" | "angle" | None)]``.
    ``max_std`` (m of tool motion): also refuse to identify a parameter whose std exceeds it.
    ``loss``: ``linear`` (least squares; touches with a standardised residual above
    ``outlier_threshold`` are excluded and the fit repeated; None: keep every touch), ``huber`` or
    ``soft_l1`` (robust losses by iteratively reweighted least squares; nothing excluded).
    ``distances``: known distances between reference points, ``[(label_a, label_b, metres[, std_m])]`` or
    ``{(label_a, label_b): metres}``: each is a weighted pseudo-observation of the fit (std: the stated
    uncertainty, default ``DISTANCE_STD``; with several fixture positions, one per position), reported in
    ``result.constraints``, and scores the holdout. ``planes``: labels whose touches lie on one unknown
    plane each (per fixture position). Per-touch weights and fixture positions come with ``obs``.
    ``touch``: how the tip meets the points (``socket``, ``needle``; instrument samples are ``tracker``): a fit far
    above what that method gives, or one that leaves the residual where it started, is not trusted and says the
    likely cause with its evidence (``result.diagnosis``; ``station.solver.misfit``).
    ``joint_noise`` (rad or m, one number or one per joint): std of the joint readings; default:
    the quantisation of the model's encoders (``station.solver.noise``); 0: none. A result carries
    ``trusted``; an untrusted one says why in ``failure``."""
    t0 = time.perf_counter()
    _check_arguments(model, obs, instrument_frame, touch, loss, noise, max_std)
    names = select_names(model, identify)
    dist = _distance_list(distances)
    prob = Problem(model, obs, names, reference, instrument_frame, dist, list(planes or []))
    _check_enough(prob, obs, names)
    prior = _prior_vector(prob, priors)
    try:
        est = _Estimation(prob, prior, noise, max_std, loss, outlier_threshold, max_iter, joint_noise)
    except ValueError as e:
        raise SolverInputError(str(e)) from None
    est.method = "tracker" if obs.measured is not None else touch
    est.run()
    res = est.result()
    if holdout is not None:
        res.holdout = holdout_mod.score(prob, est.x, est.accepted, holdout, est.sigma,
                                        {(a, b): v for a, b, v, _ in dist})
    res.settings.update(identify=identify if isinstance(identify, str) else ",".join(identify),
                        reference=_ref_setting(reference), instrument_frame=instrument_frame, noise_m=noise,
                        max_std_m=max_std, loss=loss, outlier_threshold=outlier_threshold,
                        **_fit_settings(prob, prior, dist, planes, obs, est.method, max_iter))
    res.solve_time_s = time.perf_counter() - t0
    return res


def _check_arguments(model, obs, instrument_frame: str, touch: str, loss: str, noise, max_std) -> None:
    """Refuse what no solve can use, before any work: one line naming the argument."""
    if not isinstance(obs, Observations):
        raise SolverInputError("obs must be an Observations")
    if getattr(model, "kind", "serial") == "parallel":  # station/kinematics/parallel.py
        raise SolverInputError(f"model {model.name} is a parallel robot: parametric identification needs a serial "
                               f"chain; calibrate it with 'station map' (docs/map.md)")
    if obs.q.shape[1] != model.n_joints:
        raise SolverInputError(f"model {model.name} has {model.n_joints} joints, observations have {obs.q.shape[1]}")
    if instrument_frame not in ("unknown", "base"):
        raise SolverInputError(f"instrument_frame must be 'unknown' or 'base', got {instrument_frame!r}")
    if touch not in ("socket", "needle", "tracker"):
        raise SolverInputError(f"touch must be socket, needle or tracker, got {touch!r}")
    if loss not in LOSSES:
        raise SolverInputError(f"loss must be one of {', '.join(LOSSES)}, got {loss!r}")
    if noise is not None and not (math.isfinite(noise) and noise > 0):
        raise SolverInputError(f"noise must be a positive number of metres, got {noise!r}")
    if max_std is not None and not (math.isfinite(max_std) and max_std > 0):
        raise SolverInputError(f"max_std must be a positive number of metres, got {max_std!r}")


def _check_enough(prob: Problem, obs: Observations, names: list[str]) -> None:
    """More equations than unknowns, from enough distinct poses (repeat touches in one pose add no
    independent equation about the model)."""
    m, p = int(prob.rows_per_touch.sum()) + len(prob.distances), prob.n_unknowns
    if m <= p:
        raise SolverInputError(
            f"{len(obs)} samples give {m} equations for {p} unknowns ({len(names)} model parameters"
            f"{', instrument frame' if prob.frame_unknown else ''}, {len(prob.unknown_points)} unknown point(s)"
            f"{f', {len(prob.plane_keys)} plane(s)' if prob.plane_keys else ''}); "
            f"need at least {p // 3 + 1} samples, ~20 well spread poses recommended")
    k = distinct_poses(obs.q, limit=p // 3 + 1)
    if 3 * k <= p:
        raise SolverInputError(
            f"only {k} distinct pose(s) among {len(obs)} samples (readings within {POSE_TOL * 1e3:g} mrad/um count as "
            f"one): {3 * k} equations for {p} unknowns; move the robot between touches")


def _fit_settings(prob: Problem, prior: np.ndarray, dist: list, planes, obs: Observations, method: str,
                  max_iter: int) -> dict:
    """The settings a result reports besides the caller's arguments: thresholds, priors, constraints (in the
    order the result has always listed them)."""
    return dict(rtol=RTOL, max_ratio=MAX_RATIO, runaway_prior_std=RUNAWAY, characteristic_length_m=prob.length,
                max_iter=max_iter,
                priors={n: float(prior[i]) for i, n in enumerate(prob.names) if math.isfinite(prior[i])},
                distances=[{"between": [a, b], "distance_m": v, "std_m": sd} for a, b, v, sd in dist],
                planes=list(planes or []), weighted=obs.weight is not None, fixtures=obs.fixtures, touch=method,
                estimator="maximum a posteriori, Levenberg-Marquardt on the analytic Jacobian")


DISTANCE_STD = 1e-5  # m: the uncertainty of a known distance when none is stated (a machined fixture, 10 um)


def _distance_list(distances) -> list[tuple[str, str, float, float]]:
    """``distances`` as ``[(a, b, metres, std_m)]``."""
    if not distances:
        return []
    items = [(*k, v) for k, v in distances.items()] if isinstance(distances, dict) else list(distances)
    out = []
    for it in items:
        try:
            a, b, v, *rest = it
            sd = float(rest[0]) if rest and rest[0] is not None else DISTANCE_STD
            out.append((str(a), str(b), float(v), sd))
        except (TypeError, ValueError):
            raise SolverInputError(f"distance {it!r}: expected (label_a, label_b, metres[, std_m])") from None
    return out


def _prior_vector(prob: Problem, priors) -> np.ndarray:
    prior = np.full(prob.n_unknowns, np.inf)
    model_cols = [i for i, k in enumerate(prob.kinds) if k == "model"]
    if model_cols:
        nm = [prob.names[i] for i in model_cols]
        prior[model_cols] = prior_stds(prob.model, nm, angle_params(prob.model), priors)
    return prior


class _Estimation:
    """The state of one solve: decide, fit, re-decide; outliers; final statistics."""

    def __init__(self, prob: Problem, prior, noise, max_std, loss, threshold, max_iter, joint_noise=None) -> None:
        self.prob, self.prior, self.noise, self.max_std = prob, prior.copy(), noise, max_std
        self.prior0 = prior.copy()  # as given: a prior freed by a prior-data conflict is reported with it
        self.conflicts: list[dict] = []  # prior-data conflicts: each names the data's estimate, std and what was done
        self.loss, self.threshold, self.max_iter = loss, threshold, max_iter
        self.x0 = prob.x_nominal
        self.tool = prob.tool_per_unit()  # m of tool motion per unit
        self.order = priority_order(prob.names, prob.kinds)
        N = len(prob.obs)
        self.w0 = prob.obs.weights.astype(float)  # the stated per-touch weights (1/variance scale)
        self.w = self.w0.copy()  # touch weights: those, 0 excluded (outlier), times IRLS weights for robust losses
        sq = joint_noise_of(prob.model, joint_noise)
        self.resolution = resolution_of(prob.model)
        _, self.tick_groups = quantisation(prob.obs.q, self.resolution)
        var = np.broadcast_to(sq**2, (N, len(sq)))
        self.noise_model = NoiseModel(prob.joint_jacobian(prob.x_nominal) if np.any(var > 0) else None, var, N)
        self.joint_noise = sq
        self.outliers: list[int] = []
        self.iterations = 0
        self.converged = True
        self.settled = False
        self.failure: list[str] = []
        self.notes: list[str] = []
        self.conflict: set[int] = set()  # columns in prior-data conflict (reported once)

    # ---- the loop ---------------------------------------------------------------------------------
    def run(self) -> None:
        """Fit, decide, refit until the identified set settles; a parameter the fit then puts far beyond its
        tolerance (``RUNAWAY`` prior std) although the first fit did not flag it is a prior-data conflict found
        late: freed where the data determine it, and the whole solve run again (at most twice)."""
        self._run_once()
        for _ in range(2):
            if not self._late_conflicts():
                break
            self._run_once()

    def _late_conflicts(self) -> bool:
        """Free the priors of identified parameters beyond ``RUNAWAY`` prior std that the data determine; True
        when any was freed (the caller solves again)."""
        A = self.accepted
        late = [j for j in A if math.isfinite(self.prior[j]) and abs(self.x[j] - self.x0[j]) > RUNAWAY * self.prior[j]]
        if not late:
            return False
        sigma, tfac, _ = self._sigma(self.r, len(A))
        BtB = self._btb(self.J, self.x, sigma)
        lim = self.max_std if self.max_std is not None else DETERMINED_M
        freed = []
        for j in late:
            own = self.prior.copy()
            own[j] = np.inf  # the data's std of it: its own prior out, the others' in
            post = posterior(BtB, A, [], sigma, own, tfac)
            sd = float(post.std[post.cols.index(j)])
            if sd * self.tool[j] > lim:
                continue  # the data cannot settle it: the runaway stays a failure (_trust)
            dev, pr, unit = float(self.x[j] - self.x0[j]), float(self.prior[j]), self.prob.units[j]
            self.conflicts.append({"parameter": self.prob.names[j], "data_offset": dev, "data_std": sd,
                                   "prior_std": pr, "z": abs(dev) / math.hypot(sd, pr), "freed": True, "unit": unit})
            self.conflict.add(j)
            self.prior[j] = np.inf
            freed.append(f"{self.prob.names[j]}: the data put it at {_q(dev, unit, True)} ± {_q(sd, unit)} from "
                         f"nominal ({abs(dev) / pr:.1f}x its tolerance {_q(pr, unit)})")
        if freed:
            self.notes.append(f"prior-data conflict: {'; '.join(freed)}: estimated from the data alone (prior "
                              f"freed); check the model, or state the tolerance with --prior NAME=STD")
        return bool(freed)

    def _run_once(self) -> None:
        prob = self.prob
        x, r, J = prob.initial_with_jacobian()
        self.r_before = r
        self.struct = structure(prob, x, None)
        S = sorted(self.struct.accepted)
        A = list(S)
        # The first fit weighs the prior as if the touches were perfect (1 um): nearly the plain least-squares
        # fit of everything the structure allows, so that sigma comes from the FITTED model, never from the
        # uncorrected one (whose errors would make the prior dominate and nothing look identifiable).
        sigma_w = self.noise if self.noise is not None else SIGMA_FIRST
        restructured = 0
        first = True
        seen: list[list[int]] = []  # identified sets decided so far
        frozen = False  # the decision went round in a circle: the union of the circle is kept (see below)
        for _ in range(MAX_ROUNDS):
            self.noise_model.set(sigma=sigma_w, w=self.w)
            x, r, J, it, conv = _fit(prob, x, A, self.noise_model, sigma_w, self.prior, self.x0, self.max_iter)
            self.x_cur = x
            self.iterations += it
            self.converged = conv
            sigma, tfac, dof = self._sigma(r, len(A))
            self.noise_model.set(sigma=sigma)  # the whitening that goes with this sigma
            BtB = self._btb(J, x, sigma)
            if first:
                self._conflicts(x, BtB, A, sigma)
                self.first = (r.copy(), len(A))  # residual and size of the (nearly) unconstrained fit
                first = False
            dec = decide(BtB, S, self.order, [], sigma, self.prior, self.tool, self.max_std, tfac)
            accepted = dec.accepted
            if frozen:
                accepted = A
            elif accepted != A and accepted in seen:
                # a parameter at the line is in, then out, then in again as sigma moves with it: estimate it (the
                # data carry about half its information either way; a circle must not become a failure)
                accepted, frozen = sorted(set(A) | set(accepted)), True
            seen.append(list(accepted))
            stable = accepted == A and abs(sigma / sigma_w - 1.0) < SIGMA_TOL
            if stable and self.loss != "linear":
                stable = not self._reweight(r, J, A, sigma)
            if stable:
                if self.loss == "linear" and self.threshold is not None and self._reject(r, J, A, BtB, sigma):
                    sigma_w = sigma
                    continue
                st = structure(prob, x, self.w > 0, keep=self.struct, steps=1)
                if sorted(st.accepted) != S and restructured < 2:  # the structure at the solution differs
                    restructured += 1
                    self.struct, S = st, sorted(st.accepted)
                    out = [j for j in range(prob.n_unknowns) if j not in S]
                    x[out] = self.x0[out]
                    A = list(S)  # decided again from everything the structure now allows
                    continue
                self.struct = st
                self.settled = True
                break
            for j in A:
                if j not in accepted:
                    x[j] = self.x0[j]  # back to nominal: never keep numbers for a direction the data do not see
            A, sigma_w = accepted, sigma
        self.x, self.r, self.J, self.accepted, self.S = x, r, J, A, S

    def _conflicts(self, x, BtB, A, sigma) -> None:
        """Prior-data conflict, judged on the (nearly) unconstrained first fit: the data put a parameter further
        from nominal than data and prior together allow (``CONFLICT_Z`` std of their difference). The MAP
        estimate would be dragged back by the prior and the fit left with the difference. Where the data
        determine the parameter (its std at the tool within ``max_std``, default 1 mm), its prior is freed and it
        is estimated from the data alone, reported as such; where they cannot, the result is not trusted."""
        post = posterior(BtB, A, [], sigma, np.full(len(self.prior), np.inf))
        lim = self.max_std if self.max_std is not None else DETERMINED_M
        freed, undetermined = [], []
        for i, j in enumerate(post.cols):
            pr = self.prior[j]
            if not math.isfinite(pr):
                continue
            dev, sd = float(x[j] - self.x0[j]), float(post.std[i])
            z = abs(dev) / math.hypot(sd, pr)
            if not z > CONFLICT_Z:
                continue
            unit = self.prob.units[j]
            determined = sd * self.tool[j] <= lim
            text = (f"{self.prob.names[j]}: the data put it at {_q(dev, unit, True)} ± {_q(sd, unit)} from nominal "
                    f"({abs(dev) / pr:.1f}x its tolerance {_q(pr, unit)})")
            self.conflicts.append({"parameter": self.prob.names[j], "data_offset": dev, "data_std": sd,
                                   "prior_std": float(pr), "z": z, "freed": bool(determined), "unit": unit})
            self.conflict.add(j)
            (freed if determined else undetermined).append(text)
            if determined:
                self.prior[j] = np.inf  # estimated from the data alone
        if freed:
            self.notes.append(f"prior-data conflict: {'; '.join(freed)}: estimated from the data alone (prior freed); "
                              f"check the model, or state the tolerance with --prior NAME=STD")
        if undetermined:
            self.failure.append(f"prior-data conflict the data cannot settle: {'; '.join(undetermined[:3])}"
                                f"{f' and {len(undetermined) - 3} more' if len(undetermined) > 3 else ''}: its "
                                f"std at the tool exceeds {lim * 1e3:g} mm; take more varied poses (or the model or "
                                f"the data are wrong)")

    def _btb(self, J: np.ndarray, x: np.ndarray, sigma: float) -> np.ndarray:
        """``B^T W B`` of the touches plus the known distances' information ``sigma^2 G^T G / s^2`` (so that
        ``BtB / sigma^2`` is the information of touches and distances together)."""
        Jw = self.noise_model.jacobian(J)
        out = Jw.T @ Jw
        if self.prob.distances:
            _, G, sd = self.prob.constraint_rows(x)
            Gs = G / sd[:, None]
            out = out + sigma**2 * (Gs.T @ Gs)
        return out

    def _rows(self, act: np.ndarray | None = None) -> int:
        """Residual rows of the touches kept: 3 per point touch, 1 per plane touch."""
        act = self.w > 0 if act is None else act
        return int(self.prob.rows_per_touch[act].sum())

    def _sigma(self, r: np.ndarray, n_est: int) -> tuple[float, float, int]:
        """(sigma used for the uncertainty, Student-t factor, degrees of freedom). The declared noise is
        used unless the fitted residual contradicts it (chi-square, 0.1 % level): then the fitted one."""
        m = self._rows()
        dof = max(m - n_est, 0)
        nm = self.noise_model
        if self.noise is not None:
            sd = nm.declare(self.noise)  # the declared isotropic noise plus the modelled joint noise
            rw = nm.residual(r)
            self.sigma_fit = math.sqrt(float(rw @ rw) / dof) if dof else math.inf
            if dof and self.sigma_fit > sd * math.sqrt(_chi2_upper(dof) / dof):
                self.noise_contradicted = True
                self.sigma_fit = max(nm.fit_sigma(r, dof), 1e-12)
                return self.sigma_fit, t_factor(dof), dof
            self.noise_contradicted = False
            self.sigma_declared = sd
            return sd, 1.0, dof
        fitted = max(nm.fit_sigma(r, dof), 1e-12) if dof else math.inf
        self.sigma_fit = fitted
        return fitted, t_factor(dof), dof

    def _standardised(self, r: np.ndarray, J: np.ndarray, A: list[int], BtB: np.ndarray, sigma: float):
        """Per touch: the largest externally studentised residual of its three axes, ``|r_ik| / (s_(i)
        sqrt(1 - h_ik))`` with ``s_(i)`` the residual std without touch i (one slipped touch cannot hide
        itself by inflating sigma), or the declared noise when the fit agrees with it."""
        post = posterior(BtB, A, [], sigma, self.prior)
        nm = self.noise_model
        sw = np.repeat(np.sqrt(self.w0), 3)  # a stated weight scales the touch's noise: standardise with it
        Ja = nm.jacobian(J[:, post.cols], weighted=False) * sw[:, None]
        h = np.clip(np.einsum("ij,jk,ik->i", Ja, post.info_inv, Ja) / sigma**2, 0.0, 1.0 - 1e-6)
        rt = nm.residual(r, weighted=False) * sw
        act = self.w > 0
        e = (rt**2 / (1.0 - h)).reshape(-1, 3).sum(axis=1)  # each touch's share of the residual sum
        m = self._rows(act)
        dof = m - len(A)
        rss = float(np.sum(e[act]))
        if self.noise is not None and not getattr(self, "noise_contradicted", False):
            st = np.full(len(e), self.sigma_declared)
        else:
            st = np.sqrt(np.maximum(rss - np.where(act, e, 0.0), 1e-300) / max(dof - 3, 1))
        z = (np.abs(rt) / np.sqrt(1.0 - h)).reshape(-1, 3).max(axis=1) / np.maximum(st, 1e-300)
        return z, _median(st[act])

    def _reject(self, r, J, A, BtB, sigma) -> bool:
        """Exclude touches above the threshold (all at once); True when any were excluded."""
        z, _ = self._standardised(r, J, A, BtB, sigma)
        new = [i for i in np.flatnonzero(z > self.threshold) if self.w[i] > 0]
        if not new:
            return False
        limit = int(MAX_OUTLIER_FRACTION * len(self.w))
        if len(self.outliers) + len(new) > limit:
            if "outliers" not in " ".join(self.failure):
                self.failure.append(f"{len(self.outliers) + len(new)} of {len(self.w)} touches are outliers "
                                    f"(standardised residual > {self.threshold:g}): the model does not fit these data")
            return False
        self.outliers += [int(i) for i in new]
        self.w[new] = 0.0
        return True

    def _reweight(self, r, J, A, sigma) -> bool:
        """IRLS weights of the robust loss from the current residuals; True when they changed."""
        _, st = self._standardised(r, J, A, self._btb(J, self.x_cur, sigma), sigma)
        rt = (self.noise_model.residual(r, weighted=False) * np.repeat(np.sqrt(self.w0), 3)).reshape(-1, 3)
        z = (np.linalg.norm(rt, axis=1) / (3.0 * st)) ** 2  # soft margin at 3 sigma per touch
        w = np.where(z <= 1.0, 1.0, 1.0 / np.sqrt(z)) if self.loss == "huber" else 1.0 / np.sqrt(1.0 + z)
        w = w * self.w0
        changed = bool(np.max(np.abs(w - self.w)) > 1e-3)
        self.w = w
        return changed

    # ---- the result --------------------------------------------------------------------------------
    def result(self) -> CalibrationResult:
        prob, x, r, J, A = self.prob, self.x, self.r, self.J, self.accepted
        sigma, tfac, dof = self._sigma(r, len(A))
        self.sigma = sigma
        self.noise_model.set(sigma=sigma, w=self.w)
        BtB = self._btb(J, x, sigma)
        # final decision bookkeeping: which kept parameters were weak (and how weak)
        dec = decide(BtB, self.S, self.order, [], sigma, self.prior, self.tool, self.max_std, tfac)
        kept = [j for j in range(prob.n_unknowns) if j not in A]
        extra = self._resolution(x, J)
        post = posterior(BtB, A, kept, sigma, self.prior, tfac, extra) if A else None
        std = np.full(prob.n_unknowns, np.nan)
        cov = None
        if post is not None:
            # No robust ("sandwich", HC3) inflation: on touches whose noise IS the model's it raised the stds
            # 25-60 % above the actual error spread (Monte Carlo, tests/solver/test_solver_coverage.py) - an honest
            # std must not be inflated. Noise of another shape is modelled (joint noise, noise.py) instead.
            cov = post.cov
            std[post.cols] = np.sqrt(np.maximum(np.diag(cov), 0.0))
        params: dict[str, ParameterEstimate] = {}
        info = np.full(prob.n_unknowns, np.nan)  # H_A^-1: the noise part of the variance, prior included
        if post is not None:
            info[post.cols] = np.diag(post.info_inv)
        for i, n in enumerate(prob.names):
            kind, unit = prob.kinds[i], prob.units[i]
            pr = float(self.prior0[i]) if math.isfinite(self.prior0[i]) else None
            nominal = float(self.x0[i]) if kind != "point" else math.nan
            if i in A:
                shr = None if pr is None else max(0.0, 1.0 - (std[i] / pr) ** 2)
                # the prior's share of the estimate's information (0: the data alone; freed priors count 0)
                share = None if pr is None else (0.0 if not math.isfinite(self.prior[i]) else
                                                 float(min(1.0, info[i] / self.prior[i] ** 2)))
                params[n] = ParameterEstimate(n, float(x[i]), nominal, float(std[i]), True, "", kind, unit, pr, shr,
                                              prior_share=share)
                continue
            value = nominal if kind == "model" else math.nan
            if i in self.struct.nulls:
                nl: Null = self.struct.nulls[i]
                params[n] = ParameterEstimate(n, value, nominal, None, False, nl.reason, kind, unit, pr, 0.0,
                                              nl.fix, nl.cause, prior_share=None if pr is None else 1.0)
            else:
                would, _ = dec.weak.get(i, (math.nan, pr))
                reason, fix = self._weak_reason(i, would, BtB, sigma, tfac)
                shr = None if pr is None or not math.isfinite(would) else max(0.0, 1.0 - (would / pr) ** 2)
                params[n] = ParameterEstimate(n, value, nominal, None, False, reason, kind, unit, pr, shr, fix,
                                              "weak", prior_share=None if pr is None else 1.0)
        rms0, max0 = _stats(self.r_before)
        act = self.w > 0
        rr = r.reshape(-1, 3)[act].ravel()
        rms1, max1 = _stats(rr)
        notes = list(self.notes)
        self._trust(params, dof)
        diagnosis = self._misfit(x, r, sigma, rms0, rms1)
        if diagnosis is not None:  # the cause first: conflicts and runaways are its symptoms
            self.failure.insert(0, diagnosis.pop("line"))
        if isinstance(prob.known, dict) and prob.known and prob.unknown_points:
            notes.append(f"reference point(s) {', '.join(prob.unknown_points)} not given: solved as unknown")
        if self.noise is not None and getattr(self, "noise_contradicted", False):
            notes.append(f"the fitted residual ({self.sigma_fit * 1e3:.4f} mm per axis) contradicts the declared "
                         f"noise ({self.noise * 1e3:.4f} mm): the uncertainty uses the fitted one")
        # condition number and observability index O1 of the Jacobian in metres of tool motion (angles
        # times the characteristic length), over the identified columns and the touches kept
        s = np.linalg.svd((J[:, A] / self.tool[A])[np.repeat(act, 3)], compute_uv=False) if A else np.zeros(0)
        cond = float(s[0] / s[-1]) if len(s) and s[-1] > 0 else None
        o1 = math.exp(float(np.log(s).mean())) / math.sqrt(self._rows(act)) if len(s) and s[-1] > 0 else None
        res = CalibrationResult(
            model=prob.model.name, parameters=params,
            residuals={"rms_before_m": rms0, "max_before_m": max0, "rms_after_m": rms1, "max_after_m": max1},
            rank=len(A), n_parameters=prob.n_unknowns, converged=self.converged, iterations=self.iterations,
            condition_number=cond, observability_index=o1, sigma_m=self.sigma_fit, covariance=cov,
            n_samples=len(prob.obs), n_residuals=r.size, notes=notes,
            trusted=not self.failure, failure="; ".join(self.failure) or None, conflicts=list(self.conflicts),
            diagnosis=diagnosis,
            outliers=self._outlier_list(sigma), constraints=self._constraints(x, r, post, A),
            noise={"sigma_m": sigma, "source": "declared" if self.noise is not None and not getattr(
                self, "noise_contradicted", False) else "fitted", "declared_m": self.noise,
                "fitted_m": self.sigma_fit, "dof": dof, "t_factor": tfac,
                "joint": [float(v) for v in self.joint_noise],
                "resolution": [float(v) for v in self.resolution]})
        return res

    def _misfit(self, x, r, sigma, rms0, rms1) -> dict | None:
        """Why nothing improved (``station.solver.misfit``), or None when the fit is as good as the method allows."""
        if not (math.isfinite(sigma) and math.isfinite(rms0) and math.isfinite(rms1)):
            return None
        from station.solver.misfit import explain, nothing_improved

        if not nothing_improved(rms0, rms1, sigma, self.method):
            return None  # the common case costs no Jacobian
        prob = self.prob
        obs = prob.obs
        keys = obs.point.astype(str)
        if obs.fixture is not None:
            keys = np.array([f"{p}@{f}" for p, f in zip(keys, obs.fixture.astype(str), strict=True)], dtype=object)
        Jtcp = None
        tcp = [f"tcp.{a}" for a in "xyz"]
        if not any(n in prob.names and prob.names.index(n) in self.accepted for n in tcp):
            try:
                _, _, Jp = prob.model.jacobians(obs.q, prob.full_params(x))
                Jtcp = Jp[:, :3, [prob.model.index(n) for n in tcp]]
            except (KeyError, ValueError):
                Jtcp = None
        return explain(obs.q, keys, r.reshape(-1, 3), self.w > 0, prob.joint_jacobian(x), Jtcp, rms0, rms1,
                       sigma, self.method, [j.name for j in prob.model.joints],
                       [j.revolute for j in prob.model.joints])

    def _constraints(self, x, r, post, A) -> list[dict]:
        """The known distances and planes of the fit, each with its stated and fitted value and residual."""
        prob = self.prob
        out: list[dict] = []
        cov = None if post is None else post.cov
        pos = {} if post is None else {j: i for i, j in enumerate(post.cols)}
        idx = [j for j in range(prob.n_unknowns) if j in pos]

        def std_of(row: np.ndarray) -> float | None:
            if cov is None or not idx:
                return None
            v = row[idx]
            return float(math.sqrt(max(float(v @ cov[np.ix_([pos[j] for j in idx], [pos[j] for j in idx])] @ v), 0.0)))

        if prob.distances:
            g, G, sd = prob.constraint_rows(x)
            for k, c in enumerate(prob.distances):
                out.append({"kind": "distance", "labels": [c["a"], c["b"]], "fixture": c["fixture"],
                            "stated_m": c["value"], "stated_std_m": c["std"], "fitted_m": c["value"] + float(g[k]),
                            "fitted_std_m": std_of(G[k]), "residual_m": float(g[k]),
                            "standardised": float(g[k] / sd[k])})
        if prob.plane_keys:
            P = prob.folded.evaluate(prob.obs.q, prob.full_params(x), jacobian=False)[0]
            for k, key in enumerate(prob.plane_keys):
                n, d = prob.plane_of(x, k)
                sel = prob.pslot == k
                e = P[sel] @ n - d
                act = (self.w > 0)[sel]
                c0 = prob._plane_col(k)
                row = np.zeros(prob.n_unknowns)
                row[c0 + 2] = 1.0
                ra, rb = np.zeros(prob.n_unknowns), np.zeros(prob.n_unknowns)
                ra[c0], rb[c0 + 1] = 1.0, 1.0
                sa, sb = std_of(ra), std_of(rb)
                label, _, fixture = key.partition("@")
                out.append({"kind": "plane", "labels": [label], "fixture": fixture or None,
                            "stated_m": None, "normal": [float(v) for v in n], "offset_m": d,
                            "offset_std_m": std_of(row),
                            "normal_std_rad": None if sa is None or sb is None else float(math.hypot(sa, sb)),
                            "n_touches": int(sel.sum()), "fitted_m": d,
                            "residual_m": float(np.sqrt(np.mean(e[act] ** 2))) if act.any() else None,
                            "max_residual_m": float(np.max(np.abs(e[act]))) if act.any() else None})
        return out

    def _resolution(self, x, J):
        """Consider errors for the encoders' quantisation shared by touches on one tick (``noise.quantisation``)."""
        if not self.tick_groups:
            return None
        Jq = self.prob.joint_jacobian(x)  # (N, 3, n)
        cols, var = [], []
        for j, g in self.tick_groups:
            g = g & (self.w > 0)
            if g.sum() < 1:
                continue
            col = np.zeros_like(Jq[:, :, 0])
            col[g] = Jq[g, :, j]
            cols.append(col.ravel())
            var.append(self.resolution[j] ** 2)
        if not cols:
            return None
        E = self.noise_model.jacobian(np.array(cols).T)
        return self.noise_model.jacobian(J).T @ E, np.array(var)

    def _trust(self, params: dict[str, ParameterEstimate], dof: int) -> None:
        if not self.converged:
            self.failure.insert(0, f"the fit did not converge within {self.max_iter} iterations")
        if not self.settled:
            self.failure.insert(0, f"the identified set did not settle within {MAX_ROUNDS} decide/refit rounds")
        run = []
        for i, (n, p) in enumerate(params.items()):
            if p.identifiable and p.prior_std and i not in self.conflict:
                k = abs(p.value - p.nominal) / p.prior_std
                if k > RUNAWAY:
                    run.append(f"{n} {_q(p.value - p.nominal, self.prob.units[i], True)} ({k:.1f}x its tolerance)")
        if run:
            more = f" and {len(run) - 3} more" if len(run) > 3 else ""
            self.failure.append(f"collapse or runaway: {', '.join(run[:3])}{more} from nominal")
        if dof <= 0:
            self.failure.append("no degrees of freedom left to judge the fit")

    def _weak_reason(self, j: int, would: float, BtB, sigma, tfac) -> tuple[str, str]:
        prob = self.prob
        n = prob.names[j]
        pr = self.prior[j]
        f, u = human_unit(prob.units[j])
        if not math.isfinite(would):
            post = posterior(BtB, sorted([*self.accepted, j]), [], sigma, self.prior, tfac)
            would = float(post.std[post.cols.index(j)])
        # the parameters it is most confounded with: largest posterior correlations were it estimated
        post = posterior(BtB, sorted([*self.accepted, j]), [], sigma, self.prior, tfac)
        i = post.cols.index(j)
        d = np.sqrt(np.diag(post.cov))
        corr = np.abs(post.cov[i] / (d[i] * d))
        corr[i] = 0.0
        partners = [prob.names[post.cols[k]] for k in np.argsort(-corr)[:3] if corr[k] > 0.5]
        why = (f"poorly observed: the data would leave its std at {would * f:.3g} {u} (tolerance {pr * f:.3g} {u}; "
               f"identified needs at most {MAX_RATIO:g} of the tolerance")
        if self.max_std is not None:
            why += f" and {self.max_std * 1e3:.3g} mm at the tool"
        why += ")"
        if partners:
            why += f"; correlated with {', '.join(partners)}"
        fix = "more touches (the std falls as 1/sqrt(N)), a wider spread of tool orientations, or more points"
        if n.startswith("offset.j"):
            k = int(n[8:]) - 1
            span = float(np.ptp(prob.obs.q[self.w > 0, k]))
            if prob.model.joints[k].revolute and span < math.radians(30):
                fix = f"poses that turn joint {k + 1} more (it spans {math.degrees(span):.1f} deg here); " + fix
        return why, fix

    def _outlier_list(self, sigma) -> list[dict]:
        prob = self.prob
        rr = self.r.reshape(-1, 3)
        st = self.noise if self.noise is not None else sigma
        out = []
        for i in sorted(self.outliers):
            d = float(np.linalg.norm(rr[i]))
            out.append({"index": i, "point": str(prob.obs.point[i]), "residual_m": d,
                        "standardised": float(np.max(np.abs(rr[i])) / st)})
        return out


def _q(v: float, unit: str, sign: bool = False) -> str:
    """A value for people: mm or deg."""
    k, u = human_unit(unit)
    return f"{v * k:{'+' if sign else ''}.4g} {u}"


def _chi2_upper(dof: int, z: float = 3.090232) -> float:
    """Upper 0.1 % point of chi-square (Wilson-Hilferty)."""
    a = 2.0 / (9.0 * dof)
    return dof * (1.0 - a + z * math.sqrt(a)) ** 3


def _fit(prob: Problem, x, act, noise: NoiseModel, sigma_w, prior, x0, max_iter):
    """MAP fit of the columns ``act``: minimise ``|W r|^2 + sigma_w^2 sum ((x_j - x0_j) / prior_j)^2``
    (``W`` the whitening of ``noise``). Undamped Gauss-Newton steps while they reduce the cost, Marquardt
    damping otherwise, columns equilibrated. Stops when a step is below STEP_TOL standard deviations in
    every parameter: that step is taken without another chain evaluation (the model is linear over it to
    O(step^2); the residual is the linear prediction and the Jacobian the one a step back). Returns
    ``x, r, J, iterations, converged``."""
    x = x.copy()
    r, J = prob.residual_jacobian(x)
    act = sorted(act)
    if not act:
        return x, r, J, 0, True
    pa = prior[act]
    lam = np.where(np.isfinite(pa), sigma_w**2 / np.where(np.isfinite(pa), pa, 1.0) ** 2, 0.0)
    # known distances: pseudo-observations sigma_w^2 (g / s)^2, like a prior - but never weaker than a touch:
    # the first fit's sigma_w (1 um, to let the priors go) would make a distance that fixes the scale too weak
    cons = bool(prob.distances)
    cw = max(sigma_w, float(min(c["std"] for c in prob.distances))) if cons else 0.0

    def cost(rr, xx):
        rw = noise.residual(rr)
        dx = xx[act] - x0[act]
        c = float(rw @ rw) + float(np.sum(lam * dx * dx))
        if cons:
            g, _, sd = prob.constraint_rows(xx)
            c += cw**2 * float(np.sum((g / sd) ** 2))
        return c

    c = cost(r, x)
    mu = 0.0
    n = len(act)
    eye = np.eye(n)
    for it in range(1, max_iter + 1):
        Ja = noise.jacobian(J[:, act])
        H = Ja.T @ Ja + np.diag(lam)
        g = Ja.T @ noise.residual(r) + lam * (x[act] - x0[act])
        if cons:
            gc, G, sd = prob.constraint_rows(x)
            Ga = G[:, act] / sd[:, None]
            H = H + cw**2 * (Ga.T @ Ga)
            g = g + cw**2 * (Ga.T @ (gc / sd))
        d = np.sqrt(np.diag(H))
        d = np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 1.0)
        Hs = H * np.outer(d, d)
        gs = g * d
        try:
            Hi = np.linalg.inv(Hs + mu * eye)
        except np.linalg.LinAlgError:
            Hi = np.linalg.pinv(Hs + mu * eye)
        du = -(Hi @ gs)
        dx = d * du
        std = sigma_w * np.sqrt(np.maximum(np.diag(Hi), 1e-300))  # in equilibrated units
        rel = float(np.max(np.abs(du) / std))
        x_new = x.copy()
        x_new[act] += dx
        if mu == 0.0 and (rel < STEP_TOL or float(np.max(np.abs(dx))) < XTOL):
            return x_new, r + J[:, act] @ dx, J, it, True
        r_new, J_new = prob.residual_jacobian(x_new)
        c_new = cost(r_new, x_new)
        if c_new <= c:
            small = c - c_new <= FTOL * c
            x, r, J, c = x_new, r_new, J_new, c_new
            mu = 0.0 if mu < 1e-9 else mu / 10.0
            if small or rel < STEP_TOL:
                return x, r, J, it, True
        else:
            if float(np.max(np.abs(dx))) < XTOL:
                return x, r, J, it, True  # at the minimum within rounding
            mu = max(mu * 10.0, 1e-6)
    return x, r, J, max_iter, False


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


def _ref_setting(reference):
    if isinstance(reference, str):
        return reference
    return {k: np.asarray(v, dtype=float).tolist() for k, v in dict(reference).items()}


def _stats(r: np.ndarray) -> tuple[float, float]:
    r = r.reshape(-1, 3)
    if not len(r):
        return math.nan, math.nan
    d = np.sqrt(np.einsum("ij,ij->i", r, r))
    return float(np.sqrt(np.mean(d**2))), float(d.max())


__all__ = ["Structure", "distinct_poses", "select_names", "solve"]


def _median(x: np.ndarray) -> float:
    """``np.median`` of a 1-D array, without the ``numpy.ma`` that ``np.median`` imports on first use (~30 ms of
    every ``station solve``; bench/startup.py measures it). NaN in, NaN out, as ``np.median``."""
    s = np.sort(np.asarray(x, dtype=float).ravel())
    n = len(s)
    return float("nan") if n == 0 or np.isnan(s[-1]) else float(0.5 * (s[(n - 1) // 2] + s[n // 2]))
