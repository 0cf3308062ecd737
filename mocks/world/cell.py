"""Calibration cell: fixed reference points the tool tip can touch (needle) or seat in (socket), the keep-outs the
arm's links meet, and what the integrator was told about them (positions with survey error)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

KINDS = ("socket", "needle")
CELL_FORMAT = "station-cell/1"


@dataclass(frozen=True)
class CellPoint:
    """A reference point, TRUE position in the robot base frame (m).

    ``radius`` is the contact radius of a needle or the capture radius of a socket (m); ``approach`` is
    the unit vector from the point towards where the tool comes from (e.g. up, out of a socket's cone)."""

    label: str
    kind: str  # "socket" | "needle"
    position: np.ndarray = field(repr=False)
    radius: float
    approach: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]), repr=False)

    def distance(self, p) -> float:
        return float(np.linalg.norm(np.asarray(p, dtype=float) - self.position))


# Default cells and start poses per built-in model (SI). Sockets sit where the tool reaches them from a
# wide cone of orientations (checked by tests/mocks/world/test_world_cell.py); needles point up.
DEFAULTS: dict[str, dict] = {
    "ur5e": {
        "start": [0.0, -1.5707963267948966, 1.5707963267948966, -1.5707963267948966, -1.5707963267948966, 0.0],
        "points": [
            {"label": "A", "kind": "socket", "position": [0.45, 0.0, 0.05], "approach": [0, 0, 1]},
            {"label": "B", "kind": "socket", "position": [0.35, -0.30, 0.05], "approach": [0, 0, 1]},
            {"label": "N", "kind": "needle", "position": [0.40, 0.25, 0.10], "approach": [0, 0, 1]},
        ],
    },
    "ur3e": {
        "start": [0.0, -1.5707963267948966, 1.5707963267948966, -1.5707963267948966, -1.5707963267948966, 0.0],
        "points": [
            {"label": "A", "kind": "socket", "position": [0.30, 0.0, 0.05], "approach": [0, 0, 1]},
            {"label": "N", "kind": "needle", "position": [0.25, 0.15, 0.08], "approach": [0, 0, 1]},
        ],
    },
    "ur10e": {
        "start": [0.0, -1.5707963267948966, 1.5707963267948966, -1.5707963267948966, -1.5707963267948966, 0.0],
        "points": [
            {"label": "A", "kind": "socket", "position": [0.70, 0.0, 0.05], "approach": [0, 0, 1]},
            {"label": "N", "kind": "needle", "position": [0.60, 0.35, 0.10], "approach": [0, 0, 1]},
        ],
    },
    "omx": {
        "start": [0.0, 0.0, 0.0, 0.0],
        "points": [
            {"label": "A", "kind": "socket", "position": [0.20, 0.0, 0.03], "approach": [0, 0, 1]},
            {"label": "N", "kind": "needle", "position": [0.18, 0.08, 0.05], "approach": [0, 0, 1]},
        ],
    },
    "arm6": {
        "start": [0.0, -0.5, 0.5, 0.0, 0.0, 0.0],
        "points": [
            # a tall fixture close in: the wrist cannot reach table height (d1 = 400 mm, shoulder limits), and
            # further out (e.g. 600, 0, 300 mm) the shoulder hardly varies over the tool cone, so the zero of
            # joint 2 is 10x less certain than here (checked by tests/mocks/world/test_world_cell.py)
            {"label": "A", "kind": "socket", "position": [0.35, 0.0, 0.75], "approach": [0, 0, 1]},
            {"label": "N", "kind": "needle", "position": [0.30, 0.30, 0.70], "approach": [0, 0, 1]},
        ],
    },
    "fr3": {  # Franka's "ready" pose; a two-socket fixture 50 mm apart on a table in front (ball tool)
        "start": [0.0, -0.7853981633974483, 0.0, -2.356194490192345, 0.0, 1.5707963267948966, 0.7853981633974483],
        "points": [
            {"label": "A", "kind": "socket", "position": [0.50, -0.025, 0.10], "approach": [0, 0, 1]},
            {"label": "B", "kind": "socket", "position": [0.50, 0.025, 0.10], "approach": [0, 0, 1]},
        ],
    },
    "scara": {
        "start": [0.3, 0.8, 0.05, 0.0],
        "points": [
            {"label": "A", "kind": "socket", "position": [0.40, 0.20, 0.20], "approach": [0, 0, 1]},
            {"label": "N", "kind": "needle", "position": [0.35, -0.25, 0.20], "approach": [0, 0, 1]},
        ],
    },
}


class KeepOutTruth:
    """The floor and the fixtures as the TRUE robot meets them: the truth model's link capsules against the
    world's mounting plane and keep-out volumes with zero clearance (touching is a collision). The world asks
    it about every motion the arm makes (the straight joint path between two observed configurations)."""

    STEP = 0.002  # m: no point of the arm moves more than this between two checked samples

    def __init__(self, truth, keep_out) -> None:
        from station.kinematics.collision import Checker

        self.keep_out = keep_out
        # link capsules exist for serial chains; a parallel robot's legs are not modelled as bodies (yet), so its
        # world watches nothing rather than refusing to exist
        serial = getattr(truth, "kind", "serial") != "parallel"
        self._checker = Checker(truth, keep_out) if keep_out and serial else None

    def path(self, q_from, q_to):
        """The first contact along ``q_from -> q_to`` (a ``Hit``), or None. An arm already in contact may move
        (out of it: the fault was latched when it got there)."""
        if self._checker is None:
            return None
        q_from, q_to = np.asarray(q_from, float), np.asarray(q_to, float)
        if self._checker.hits(q_from[None])[0] is not None:
            return None
        return self._checker.path_hit(q_from, q_to, step=self.STEP)


class Cell:
    """The reference points as they truly are (``points``, m) and as the integrator surveyed them (``survey``:
    the error of each), with the contact rules the world applies to the true tip: which needle it touches,
    which socket captures it and where in that socket it settles (seating noise, its own random stream)."""

    def __init__(self, spec, g_survey: np.random.Generator, g_seat: np.random.Generator) -> None:
        self.spec = spec
        self.points: dict[str, CellPoint] = {}
        self.survey: dict[str, np.ndarray] = {}
        for p in spec.points:
            radius = p["radius"] or (spec.capture_radius if p["kind"] == "socket" else spec.contact_radius)
            self.points[p["label"]] = CellPoint(p["label"], p["kind"], np.array(p["position"], dtype=float),
                                                float(radius), np.array(p["approach"], dtype=float))
            self.survey[p["label"]] = g_survey.normal(0.0, spec.survey_sigma, 3)
        self._g_seat = g_seat

    def capturing(self, tip) -> CellPoint | None:
        """The socket whose capture radius holds ``tip`` (the nearest of several), or None."""
        sockets = [p for p in self.points.values() if p.kind == "socket" and p.distance(tip) <= p.radius]
        return min(sockets, key=lambda s: s.distance(tip)) if sockets else None

    def settling_point(self, socket: CellPoint) -> np.ndarray:
        """Where the compliant tip comes to rest in ``socket`` this time: its centre plus seating noise (m)."""
        return socket.position + self._g_seat.normal(0.0, self.spec.seating_sigma, 3)

    def needle_touched(self, tip) -> str | None:
        """Label of the needle whose contact radius holds ``tip``, or None."""
        for p in self.points.values():
            if p.kind == "needle" and p.distance(tip) <= p.radius:
                return p.label
        return None

    def station_doc(self, nominal) -> dict:
        """The cell as the integrator knows it (``station-cell/1``): approximate positions in the robot
        base frame = true + survey error, rounded to 0.1 mm."""
        pts = []
        for label, p in self.points.items():
            pos = p.position + self.survey[label]
            pts.append({"label": label, "kind": p.kind, "position": [round(float(x), 4) for x in pos],
                        "approach": [round(float(x), 6) for x in p.approach],
                        "radius": round(p.radius, 6)})
        tool = {k: round(nominal.param(f"tcp.{k}"), 6) for k in ("x", "y", "z", "rx", "ry", "rz")
                if f"tcp.{k}" in nominal.param_names}  # the planar parallel robot has no tool frame
        from station.kinematics.collision import DEFAULT_CLEARANCE, keep_out_to_doc

        # the floor and fixtures as built (no survey error), with the station's default clearance around them
        return {"format": CELL_FORMAT, "units": {"length": "m", "angle": "rad"}, "frame": "robot base",
                "model": nominal.name, "tool": tool, "survey_sigma": self.spec.survey_sigma,
                "points": pts, **keep_out_to_doc(self.spec.keep_out, clearance=DEFAULT_CLEARANCE)}
