"""Sample sets PM (docs/map.md; its source's [0028]-[0034]): the grid of actuator levels (or, the same nodes,
the corners of its Kuhn simplices). Configurations the nominal model cannot assemble are left out and reported."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from station.solver.map.grid import MESHES, Grid, grid_levels


@dataclass(frozen=True)
class Plan:
    model: str
    mesh: str  # "grid" (multilinear) or "simplex" (barycentric on the Kuhn simplices)
    q: tuple[int, ...]  # sub-intervals per actuator
    exclude_ends: bool
    levels: tuple[np.ndarray, ...]
    x: np.ndarray  # (N, n) configurations to visit, grid order (last actuator fastest), SI
    dropped: np.ndarray  # (M, n) grid nodes the nominal model cannot assemble
    reasons: tuple[str, ...]  # why, one per dropped node

    @property
    def grid(self) -> Grid:
        return Grid(self.levels)


BOUNDARY_MARGIN = 0.02  # of the actuator range: nodes this close to the workspace boundary are left out
SERIAL_COND = 1e3  # serial arms: nodes whose joint Jacobian is worse conditioned are left out (near a singularity)


def plan(model, q, *, exclude_ends: bool = False, mesh: str = "grid", lower=None, upper=None,
         margin: float = BOUNDARY_MARGIN) -> Plan:
    """The sample set over the actuator box ``[lower, upper]`` (default: the model's limits). ``q``: one Q
    for every actuator or one per actuator (Q sub-intervals, Q + 1 levels; Q - 1 without the ends).

    A serial arm assembles everywhere, but near a singularity IK(GDK(x)) is not unique and a small pose error
    becomes a large summand: nodes whose joint Jacobian (rotation rows scaled by the reach) has a condition
    number above ``SERIAL_COND`` are left out. A parallel robot's workspace is not a box in actuator space:
    nodes the nominal model cannot assemble are left out, and so are nodes within ``margin`` (a fraction of
    the actuator range) of the workspace boundary, where the real robot, whose geometry differs, may not
    assemble: the actuators are moved by that much both ways along the direction the platform follows worst
    (the largest singular direction of the forward Jacobian) and both must assemble."""
    if mesh not in MESHES:
        raise ValueError(f"mesh must be one of {', '.join(MESHES)}, got {mesh!r}")
    lo = model.lower if lower is None else np.asarray(lower, dtype=float)
    hi = model.upper if upper is None else np.asarray(upper, dtype=float)
    if np.any(lo < model.lower - 1e-12) or np.any(hi > model.upper + 1e-12) or np.any(lo >= hi):
        raise ValueError("the sampled box must lie inside the actuator limits, lower below upper")
    qs = tuple(int(v) for v in np.broadcast_to(np.asarray(q, dtype=int), (model.n_joints,)))
    levels = tuple(grid_levels(lo, hi, qs, exclude_ends))
    nodes = Grid(levels).nodes()
    ok = np.ones(len(nodes), dtype=bool)
    reasons: list[str] = [""] * len(nodes)
    if getattr(model, "kind", "serial") == "parallel":
        res = model.fk_solve(nodes)
        ok, reasons = res.ok.copy(), list(res.reason)
        idx = np.flatnonzero(ok)
        if idx.size and margin > 0:
            Jq = model.jacobians(nodes[idx], guess=res.T[idx])[1]
            weak = np.linalg.svd(Jq)[2][:, 0, :]  # (N, n) actuator direction of the largest pose change
            step = margin * float(np.mean(model.upper - model.lower))
            for sign in (1.0, -1.0):
                near = model.fk_solve(nodes[idx] + sign * step * weak, guess=res.T[idx])
                for j in np.flatnonzero(~near.ok):
                    i = idx[j]
                    if ok[i]:
                        ok[i] = False
                        reasons[i] = (f"within {step:.4g} m of the workspace boundary (the real robot may not "
                                      f"assemble there)")
    else:
        T, Jq, _ = model.jacobians(nodes)
        reach = max(float(np.max(np.linalg.norm(T[:, :3, 3], axis=1))), 1e-3)
        J = Jq if model.n_joints > 3 else Jq[:, :3]
        if model.n_joints > 3:
            J = J * np.r_[np.ones(3), np.full(3, reach)][None, :, None]
        s = np.linalg.svd(J, compute_uv=False)
        cond = s[:, 0] / np.maximum(s[:, -1], 1e-300)
        ok = cond <= SERIAL_COND
        reasons = ["" if k else f"near a singularity (condition number {c:.3g})" for k, c in zip(ok, cond, strict=True)]
    return Plan(model.name, mesh, qs, bool(exclude_ends), levels, nodes[ok], nodes[~ok],
                tuple(r for r, k in zip(reasons, ok, strict=True) if not k))


def predicted_residual(model, p: Plan, n_probe: int = 200, seed: int = 0) -> float:
    """How much of a pose error a serial arm's map built on plan ``p`` would leave, before anything moves.

    The map interpolates summands KSF = J(x)^-1 e; near a singularity (a 6R arm's wrist centre near axis 1,
    a stretched elbow, a straight wrist) J^-1 grows like 1/distance, and interpolating such a pole between
    the grid nodes fails even for exact, noise-free measurements. This replays that for the 12 constant unit
    pose errors (3 translations and 3 rotations, in the base and in the tool frame; a rotation counts
    ``reach`` metres per radian): their exact summands at every grid node, interpolated to random probe
    configurations inside the box (as the held-out ones), mapped back through the probe's Jacobian. The
    answer is the RMS fraction of the error left (0: the map would correct it exactly; 1: as if no map).
    Scale-free and independent of the actual errors to first order; the real robots' errors, which partly
    look like joint offsets the map holds exactly, leave about a third of it (docs/map.md)."""
    from station.solver.map.grid import Grid

    grid = Grid(p.levels)
    nodes = grid.nodes()
    T, J, _ = model.jacobians(nodes)
    reach = max(float(np.max(np.linalg.norm(T[:, :3, 3], axis=1))), 1e-3)
    scale = np.r_[np.ones(3), np.full(3, reach)]

    def unit_errors(R):  # (N, 12, 6): unit pose errors in the base frame, then in the tool frame
        tool = np.zeros((len(R), 6, 6))
        tool[:, :3, :3] = np.swapaxes(R, 1, 2)
        tool[:, 3:, 3:] = np.swapaxes(R, 1, 2)
        return np.concatenate([np.broadcast_to(np.eye(6), (len(R), 6, 6)), tool], axis=1)

    try:
        S = np.linalg.solve((J * scale[None, :, None])[:, None], unit_errors(T[:, :3, :3])[..., None])[..., 0]
    except np.linalg.LinAlgError:  # a node exactly at a singularity
        return float("inf")
    rng = np.random.default_rng(seed)
    lo, hi = grid.lower, grid.upper
    inset = 0.1 * (hi - lo)
    xp = rng.uniform(lo + inset, hi - inset, (n_probe, model.n_joints))
    Si = grid.interpolate(S.reshape(len(nodes), -1), xp, p.mesh).reshape(n_probe, 12, -1)
    Tp, Jp, _ = model.jacobians(xp)
    left = np.einsum("nij,nkj->nki", Jp * scale[None, :, None], Si) - unit_errors(Tp[:, :3, :3])
    return float(np.sqrt(np.mean(np.sum(left ** 2, axis=2))))
