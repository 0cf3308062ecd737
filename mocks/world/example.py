"""``station mock world example``: a complete, commented world file for a built-in model (mm, deg)."""

from __future__ import annotations

import math

from station.mocks.world.cell import DEFAULTS
from station.mocks.world.world import DEFAULT_SIGMAS

# Sockets the example adds to a built-in 6-axis arm's default cell so that it has three (dh_full needs three spread
# over the workspace): placed by mocks/world/reach.py (35 deg cone, limits, links clear of the floor, on the side
# of socket A, as far from the cell's points as reach allows); test_world_example_own_arm.py checks them with
# the engine's planner. Built-in worlds (World.default) keep their cells.
EXTRA_SOCKETS = {
    "ur3e": [("B", [0.0, -0.363, 0.337]), ("C", [0.0, 0.363, 0.337])],
    "ur5e": [("C", [0.0, 0.599, 0.556])],
    "ur10e": [("B", [0.0, -0.848, 0.788]), ("C", [0.0, 0.848, 0.788])],
    "arm6": [("B", [0.0, -0.621, 0.399]), ("C", [0.0, 0.621, 0.399])],
}


def _mm(x: float) -> str:
    return f"{x * 1e3:g}"


def _example_cell(m, builtin: bool, seed: int) -> tuple[dict, str]:
    """The example's start pose and cell points (SI), and a comment on where they came from: a built-in
    model's default cell (with EXTRA_SOCKETS), a parallel robot's home (its points measured by a tracker), or a
    cell computed from the workspace of an arm of one's own."""
    d = DEFAULTS.get(m.name) if builtin else None
    if d is not None and m.name in EXTRA_SOCKETS:
        d = {**d, "points": [*d["points"], *({"label": lb, "kind": "socket", "position": p, "approach": [0, 0, 1]}
                                            for lb, p in EXTRA_SOCKETS[m.name])]}
    if d is not None:
        return d, ""
    if getattr(m, "kind", "serial") == "parallel":
        return {"start": list(m.home_q), "points": []}, ""
    from station.mocks.world.reach import place_points

    placed = place_points(m, seed=seed)
    d = {"start": [round(x, 3) if not j.revolute else math.radians(round(math.degrees(x), 1))
                   for x, j in zip(placed.start, m.joints, strict=True)], "points": placed.points}
    return d, (f"  # computed for {m.name} (reach {placed.reach * 1e3:.0f} mm): reached from a 35 deg cone of "
               "tool directions, links clear of the floor" + (f"; {placed.note}" if placed.note else ""))


def example_text(model: str = "ur5e", seed: int = 0, tip_link: str | None = None,
                 base_link: str | None = None) -> str:
    from station.kinematics import builtin_names, load_model

    m = load_model(model, tip_link=tip_link, base_link=base_link)
    ref = m.name if model in builtin_names() else str(model)  # a model file: keep its path
    d, note = _example_cell(m, model in builtin_names(), seed)
    start = ", ".join(f"{math.degrees(x):g}" if j.revolute else _mm(x) for x, j in zip(d["start"], m.joints,
                                                                                       strict=True))
    pts = "\n".join(
        f"    - {{label: {p['label']}, kind: {p['kind']}, position: [{', '.join(_mm(x) for x in p['position'])}], "
        f"approach: [{', '.join(f'{a:g}' for a in p['approach'])}]}}" for p in d["points"]) or "    []"
    note = f"{note}\n" if note else ""
    links = "".join(f"  {k}: {v}\n" for k, v in (("tip_link", tip_link), ("base_link", base_link)) if v)
    sj = m.joints[1].name
    o, dh, tcp = DEFAULT_SIGMAS["offsets"], DEFAULT_SIGMAS["dh"], DEFAULT_SIGMAS["tcp"]
    link = next((n for n in m.param_names if n.endswith(".a") and abs(m.param(n)) > 0),
                m.param_names[7] if len(m.param_names) > 7 else m.groups["dh"][-1])
    off = m.groups["offsets"][1]  # offset.j2 (serial), leg.2.offset / strut.2.offset (parallel)
    off_line = (f"{off}: 0.05            # deg: joint zero offset (theta = q + offset)" if m.joints[1].revolute else
                f"{off}: 0.05       # mm: actuator zero offset (length = q + offset)")
    n = m.n_joints  # one device per joint on every bus, or the emulator refuses its own world file
    ids = ", ".join(str(11 + i) for i in range(n))
    nodes = ", ".join(str(1 + i) for i in range(n))
    return f"""\
# station simulated world (station-world/1): the robot the emulators serve, with errors only you know.
# Use it with any emulator:  station mock <bus> --world THIS_FILE ; inspect it:  station mock world show THIS_FILE
# Units: every length below is in units.length, every angle in units.angle; time in s, mass in kg.
format: station-world/1
description: example world for {m.name}
units: {{length: mm, angle: deg, time: s, mass: kg}}
seed: {seed}                     # seeds every random draw (hidden errors, seating noise, survey error, encoder noise)

robot:
  model: {ref}                 # built-in name ({m.name}, ...) or a station-model/1 file (relative to this file)
{links}  # tool: {{x: 0, y: 0, z: 0, rx: 0, ry: 0, rz: 0}}   # nominal tool (TCP) frame on the flange (default: model's)

errors:                        # hidden: truth = nominal + error (the station does not know them)
  explicit:                    # by parameter name (station model show {m.name} lists them); mm or deg by kind
    {off_line}
    {link}: 0.3               # mm
  random:                      # group, name or glob -> sigma of a zero-mean normal draw per parameter
    offsets: {{length: {_mm(o['length'])}, angle: {math.degrees(o['angle']):g}}}   # mm for prismatic, deg for revolute
    dh: {{length: {_mm(dh['length'])}, angle: {math.degrees(dh['angle']):g}}}   # link geometry a, d, alpha, beta
    tcp: {_mm(tcp['length'])}                   # mm, tool position
  # explicit values replace the random draw of the same parameter

joints:                        # mechanics between motor encoder and link; all off by default
  backlash: {{}}                 # e.g. {{{sj}: 0.02}}: full dead band, deg (mm for prismatic joints)
  compliance: {{}}               # e.g. {{{sj}: 0.0001}}: deg per N*m of gravity torque (default: the model's)
  masses: {{}}                   # e.g. {{{sj}: {{mass: 8.0, com: [212, 0, 113]}}}}: kg, centre in the link frame (mm)
  payload: 0                   # kg at the tool tip, or {{mass: kg, com: [x, y, z]}} (loads the compliant joints)
  gravity: [0, 0, -9.81]       # m/s^2 in the robot base frame

motion:
  time_mode: instant           # instant: moves complete at once | sim: time passes with world.advance(dt)
                               # | realtime: state follows the wall clock
  time_scale: 1                # realtime only: world seconds per wall second
  start: [{start}]   # encoder positions at power-on (deg; mm for prismatic)
  enabled: true                # joints powered at start

cell:                          # reference points in the robot base frame (true positions, mm)
  contact_radius: 0.05         # mm: needle contact input closes within this distance of the needle tip
  capture_radius: 8            # mm: a socket seats the compliant tip from within this distance
  points:                      # kind socket (ball-in-cone) or needle; approach: unit vector towards the tool
{note}{pts}
    # per point, radius: overrides the contact (needle) or capture (socket) radius, mm

noise:
  seating: 0.01                # mm, sigma per axis of where the tip settles in a socket
  survey: 0                    # mm, sigma per axis of the cell positions given to the station (station-cell)
  encoder: 0                   # deg (mm for prismatic), sigma of each encoder reading

buses:                         # passed through to the bus emulators (world.bus_config(name))
  dynamixel: {{baud: 1000000, ids: [{ids}]}}   # one servo per joint
  canopen: {{nodes: [{nodes}]}}           # one CiA 402 drive per joint
  ur: {{}}                       # serial: derived from this world (its arm and cell) unless given here
"""
