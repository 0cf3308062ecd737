"""Sample sets PM of seed 004 ([0028]-[0034]): the grid of actuator levels (or, the same nodes, the corners of
its Kuhn simplices). Configurations the nominal model cannot assemble are left out and reported."""

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
