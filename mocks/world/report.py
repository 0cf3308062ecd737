"""``station mock world show``: the hidden truth as text (what only the person who staged the world knows)."""

from __future__ import annotations

import numpy as np
from station.mocks.world.worldfile import ANGLE, LENGTH, param_kind


def truth_report(world, length: str = "mm", angle: str = "deg") -> str:
    L, A = 1 / LENGTH[length], 1 / ANGLE[angle]
    nom = world.nominal
    lines = [f"world: model {nom.name} ({nom.convention}), seed {world.spec.seed}, time mode {world.time_mode}"
             f" (scale {world.time_scale:g})", "",
             f"hidden errors ({len(world.errors())} parameters; lengths in {length}, angles in {angle}):",
             f"  {'parameter':<18} {'nominal':>14} {'true':>14} {'difference':>14}"]
    for name, err in world.errors().items():
        u = L if param_kind(nom, name) == "length" else A
        unit = length if u == L else angle
        lines.append(f"  {name:<18} {nom.param(name) * u:>14.6f} {world.truth.param(name) * u:>14.6f} "
                     f"{err * u:>+14.6f} {unit}")
    s = world.spec
    mech = []
    for i in range(world.n_joints):
        j = world.truth.joints[i]
        u, unit = (A, angle) if j.revolute else (L, length)
        if s.backlash.get(i):
            mech.append(f"  backlash {j.name}: {s.backlash[i] * u:.6f} {unit} (full width)")
        if s.compliance.get(i):
            mech.append(f"  compliance {j.name}: {s.compliance[i] * u:.3e} {unit}/(N*m)")
    grav = world.gravity
    for k, (m, c) in sorted(grav.masses.items()):
        if m > 0:
            mech.append(f"  mass of link {k} ({world.truth.joints[k - 1].name}): {m:g} kg at "
                        f"[{', '.join(f'{x * L:.4f}' for x in c)}] {length} (link frame)")
    if mech or grav.payload[0] > 0:
        pc = ", ".join(f"{x * L:.4f}" for x in grav.payload[1])
        lines += ["", f"joint mechanics (payload {grav.payload[0]:g} kg at [{pc}] {length} in the tool frame; "
                      f"gravity deflection {'on' if grav.active else 'off'}):", *mech]
    cell = world.station_cell()
    station = {p["label"]: p for p in cell["points"]}
    lines += ["", f"cell points (true and station-side positions in {length}; survey sigma "
                  f"{s.survey_sigma * L:g} {length}):",
              f"  {'label':<6} {'kind':<7} {'true x':>10} {'true y':>10} {'true z':>10}   "
              f"{'station x':>10} {'station y':>10} {'station z':>10} {'radius':>8}"]
    for label, p in world.points.items():
        t = p.position * L
        st = np.array(station[label]["position"]) * L
        lines.append(f"  {label:<6} {p.kind:<7} {t[0]:>10.4f} {t[1]:>10.4f} {t[2]:>10.4f}   "
                     f"{st[0]:>10.4f} {st[1]:>10.4f} {st[2]:>10.4f} {p.radius * L:>8.4f}")
    lines += ["", f"noise: seating sigma {s.seating_sigma * L:g} {length}/axis, encoder sigma "
                  f"{s.encoder_sigma * A:g} {angle}"]
    q = world.encoder_q()
    lines.append("start/current encoder q: " + ", ".join(
        f"{x * (A if j.revolute else L):.4f}" for x, j in zip(q, world.truth.joints, strict=True)))
    lines.append(f"true tip now: {', '.join(f'{x * L:.4f}' for x in world.tip_true())} {length}")
    return "\n".join(lines)
