"""What each panel of the jog UI shows, as rich ``Text`` from the controller's state: one function per panel,
each in a wide form and a compact one (an 80x24 terminal: two 40-column halves). No widgets here; the app
(``station.tui.app``) places them and redraws a panel only when its text changed."""

from __future__ import annotations

import re

import numpy as np
from rich.text import Text

from station.tui.controller import STEP_PRESETS, JogController
from station.units import human, human_of, joint_quantity

# (plus key, minus key) per axis: J1..J6 in joint mode, X Y Z Rx Ry Rz in Cartesian mode
JOG_KEYS = (("q", "a"), ("w", "s"), ("e", "d"), ("r", "f"), ("t", "g"), ("y", "h"), ("u", "j"))
SEAT_KEY = "v"
NEAR_KEY = "n"
SHORT = {"forced_samples": "forced", "offset_std_max": "offset-σ", "offset_abs_max": "offset", "fit_rms": "fit",
         "fit_max": "fit-max"}  # check names in the compact guidance
GUIDE_COLOURS = {"good enough": "bold black on green", "not yet": "bold yellow", "NO LIMITS": "bold white on magenta"}


def _fmt_value(v: float, rotational: bool) -> str:
    unit, k = human(joint_quantity(rotational))
    return f"{v * k:+10.3f} {unit:<3}"


def _mm(v: float) -> str:
    """A distance in mm with the digits a technician jogging by 0.01-10 mm steps needs."""
    mm = round(abs(v) * 1e3, 2)
    v = v + 0.0 if mm else 0.0  # no "-0.00"
    return f"{v * 1e3:.2f}" if mm < 10 else (f"{v * 1e3:.1f}" if mm < 100 else f"{v * 1e3:.0f}")


def title_text(ctl: JogController, compact: bool) -> Text:
    t = Text()
    t.append(" station jog ", style="bold reverse")
    header = getattr(ctl.session.journal, "header", None)
    serial = getattr(header, "serial", None)
    t.append(f" {ctl.model.name}" + (f" · serial {serial}" if serial else ""))
    if not compact:
        t.append(f" · session {ctl.session.id}", style="dim")
    return t


def help_line(compact: bool) -> Text:
    """The station's own key help at the bottom (textual's footer would list framework keys)."""
    t = Text()
    items = [("space/^c", "STOP"), ("⏎", "record"), (SEAT_KEY, "seat"), (NEAR_KEY, "near"), ("p", "point"),
             ("?", "keys"), ("^q", "quit")]
    if not compact:
        items[5:5] = [("m", "joint|cart"), ("1-4", "step"), ("0", "hold"), ("-+", "speed"), ("!", "forced")]
    for i, (key, what) in enumerate(items):
        if i:
            t.append("  ")
        t.append(f" {key} " if what == "STOP" else key, style="bold reverse red" if what == "STOP" else "bold")
        t.append(f" {what}")
    return t


def keys_text(ctl: JogController, compact: bool = False) -> Text:
    n = max(ctl.model.n_joints, 6)
    pairs = " ".join(f"{p}/{m}" for p, m in JOG_KEYS[:n])
    seat = f"{ctl.compliant_name}" if ctl.can_seat else "n/a on this robot"
    if compact:  # the essentials in 36 columns, most wanted first; ? shows them all
        return Text.from_markup(
            f"[b]{NEAR_KEY}[/b] near  [b]{SEAT_KEY}[/b] seat  [b]![/b] forced  [b]k[/b] retake\n"
            f"[b]{JOG_KEYS[0][0]}/{JOG_KEYS[0][1]}..{JOG_KEYS[n - 1][0]}/{JOG_KEYS[n - 1][1]}[/b] axis±  "
            "[b]1-4[/b] step  [b]m[/b] mode\n"
            "[b]-+[/b] speed  [b]0[/b] hold  [b]del[/b] discard\n"
            "[b]↑↓[/b] sample  [b]PgDn[/b] solve  [b]W[/b] write\n"
            "[b]c[/b] clear fault  [b]?[/b] all keys")
    return Text.from_markup(
        f"[b]{pairs}[/b] axis 1..{n} +/-\n[b]m[/b] joint|Cart  [b]o[/b] base|tool frame  [b]- +[/b] speed %\n"
        f"[b]1 2 3 4[/b] step {' / '.join(f'{s:g}' for s in STEP_PRESETS)} mm|deg  [b]0[/b] hold-to-run\n"
        f"[b]p P[/b] point  [b]{NEAR_KEY}[/b] go near it  [b]{SEAT_KEY}[/b] seat ({seat})\n"
        "[b]enter[/b] record  [b]![/b] record w/o contact (forced)\n"
        "[b]↑ ↓[/b] select  [b]k[/b] retake  [b]del[/b] discard  [b]W[/b] write\n"
        "[b]PgUp PgDn[/b] scroll the solve  [b]?[/b] all keys  [b]c[/b] clear fault\n"
        "[b][reverse] space [/reverse][/b] or [b][reverse] ctrl+c [/reverse][/b] STOP (x)   [b]ctrl+q[/b] quit")


def joints_text(ctl: JogController, compact: bool) -> Text:
    r = ctl.readout
    t = Text()
    if r is None:
        return t
    cells = []
    for i, j in enumerate(ctl.model.joints):
        style = "bold" if ctl.mode == "joint" and i == ctl.axis else ""
        unit, k = human(joint_quantity(j.revolute))
        if compact:
            cells.append((f"J{i + 1} {r.q[i] * k:+9.3f} {'°' if unit == 'deg' else unit}", style))
            continue
        lo, hi = (np.rad2deg([j.lower, j.upper]) if j.revolute else np.array([j.lower, j.upper]) * 1e3)
        t.append(f"J{i + 1} {j.name[:8]:<8}{_fmt_value(r.q[i], j.revolute)}", style=style)
        t.append(f"  [{lo:.0f}, {hi:.0f}]\n", style="dim")
    if compact:  # two joints a line: J1 J4 / J2 J5 / J3 J6
        half = (len(cells) + 1) // 2
        for row in range(half):
            for col, idx in enumerate((row, row + half)):
                if idx < len(cells):
                    t.append(("  " if col else "") + f"{cells[idx][0]:<16}", style=cells[idx][1])
            t.append("\n")
    t.rstrip()
    return t


def tcp_text(ctl: JogController, compact: bool) -> Text:
    r = ctl.readout
    t = Text()
    if r is None:
        return t
    x, y, z = r.tcp[:3] * 1e3
    if ctl.ur_rotvec:  # as the UR pendant shows it: rotation vector in rad
        (rx, ry, rz), u = r.tcp[3:], "rad"
    else:
        (rx, ry, rz), u = np.rad2deg(r.tcp[3:]), "deg"
    if compact:
        t.append(f"X{x:+9.2f} Y{y:+9.2f} Z{z:+9.2f} mm\nRx{rx:+8.4f} Ry{ry:+8.4f} Rz{rz:+8.4f}")
        t.append(f" {u}", style="dim")
        return t
    t.append(f"X {x:+10.3f} mm   Rx {rx:+9.4f} {u}\nY {y:+10.3f} mm   Ry {ry:+9.4f} {u}\n"
             f"Z {z:+10.3f} mm   Rz {rz:+9.4f} {u}")
    return t


def tcp_title(ctl: JogController, compact: bool) -> str:
    rot = "rotation vector, as UR" if ctl.ur_rotvec else "roll-pitch-yaw"
    return "TCP (nominal FK)" if compact else f"TCP (nominal FK, base frame; {rot})"[:54]


def _touch(ctl: JogController, t: Text) -> None:
    r = ctl.readout
    if ctl.stale:
        t.append(" ? no reading ", style="reverse red")
    elif r is None or r.touch is None:
        t.append(" no contact input ", style="reverse dim")
    elif r.touch:
        t.append(" ● CONTACT ", style="bold black on green")
    else:
        t.append(" ○ no contact ", style="dim")


def _arm_state(ctl: JogController, t: Text, compact: bool) -> None:
    p = ctl.proximity
    if not ctl.can_seat:
        t.append("arm stiff", style="dim")
        t.append("" if compact else f" ({ctl.compliant_name} mode: none on this robot)", style="dim")
    elif ctl.compliant:
        t.append(f" {ctl.compliant_name.upper()} ", style="bold black on yellow")
        t.append(f" {SEAT_KEY}: hold stiff", style="yellow")
    elif p is not None and p.within and p.kind == "socket":
        t.append("arm stiff", style="green")
        t.append(f"  in capture radius: {SEAT_KEY} seats", style="bold green")
    else:
        t.append("arm stiff", style="green")
        t.append(f"  {SEAT_KEY}: {ctl.compliant_name}", style="dim")


def _proximity(ctl: JogController, t: Text, compact: bool) -> None:
    p = ctl.proximity
    if p is None:
        if ctl.point not in ctl.targets:
            t.append(f"{ctl.point}: no nominal position" + ("" if compact else
                     f" (cell file, or --reference {ctl.point}=x,y,z)"), style="dim")
        return
    style = "bold green" if p.within else "bold"
    t.append(f"to {p.label}: ")
    t.append(f"{_mm(p.distance)} mm", style=style)
    # "above"/"below" along the point's approach direction (up for a socket in a table); below it and close to
    # its axis means the tool would be pushing through the point
    where = "above" if p.above >= 0 else "below"
    t.append(f", {_mm(abs(p.above))} {where}, {_mm(p.lateral)} " + ("off" if compact else "off its axis"),
             style="bold red" if p.above < 0 and p.lateral < 0.01 else "")
    t.append("\n")
    dx, dy, dz = (("" if v.startswith("-") else "+") + v for v in map(_mm, p.delta))
    t.append(f"go X{dx} Y{dy} Z{dz}", style="cyan")
    t.append(f" ({p.frame})" if compact else f" ({p.frame} frame)", style="dim")
    if p.kind == "needle" and p.distance < 0.002:
        t.append("  fine steps (2, 1)", style="bold yellow")
    elif not compact and p.label not in ctl.blocked:
        t.append(f"   {NEAR_KEY}: go near", style="dim")


def jog_text(ctl: JogController, compact: bool) -> Text:
    r = ctl.readout
    t = Text()
    if compact:
        t.append("joint" if ctl.mode == "joint" else f"cart {ctl.frame}", style="bold cyan")
        t.append(" · ")
        t.append("hold-to-run" if ctl.continuous else f"step {ctl.step:g}", style="bold cyan")
        t.append(" · ")
        t.append(f"{ctl.speed_percent}% {ctl.speed_mm_s:g} mm/s\n", style="bold cyan")
        t.append(f"{ctl.point}", style="bold magenta")
        target = ctl.targets.get(ctl.point)
        t.append(f" {target.kind if target is not None else ''} ")
    else:
        t.append("mode  ")
        t.append(f"{ctl.mode:<10}", style="bold cyan")
        if ctl.mode == "cartesian":
            t.append(f"{ctl.frame} frame  ", style="bold cyan")
        t.append("step  " if not ctl.continuous else "")
        t.append("hold-to-run\n" if ctl.continuous else f"{ctl.step:g} mm | deg\n", style="bold cyan")
        t.append("speed ")
        t.append(f"{ctl.speed_percent} % = {ctl.speed_mm_s:g} mm/s", style="bold cyan")
        t.append(" (max 250)  point ")
        t.append(f"{ctl.point}", style="bold magenta")
        target = ctl.targets.get(ctl.point)
        t.append(f" {target.kind}\n" if target is not None else "\n")
        t.append("touch ")
    _touch(ctl, t)
    if ctl.near is not None:
        state, colour = "going near" if compact else f"going near {ctl.near.plan.label}", "yellow"
    elif r is not None and not r.enabled and not ctl.stale:
        state, colour = "disabled (c)", "red"
    else:
        state = "no reading" if ctl.stale else ("moving" if r and r.moving else "still")
        colour = "green" if state == "still" else "yellow"
    t.append(f" {state}", style=colour)
    t.append("\n")
    _arm_state(ctl, t, compact)
    t.append("\n")
    _proximity(ctl, t, compact)
    t.rstrip()
    return t


def guide_text(ctl: JogController, compact: bool) -> Text:
    g = ctl.guide
    t = Text()
    if compact:
        for i, label in enumerate(ctl.labels):
            if i:
                t.append("  ")
            mark = "▶" if label == g.next_point else ("✗" if label in g.blocked else " ")
            t.append(f"{mark}{label}", style="bold magenta" if label == ctl.point else
                     ("dim" if label in g.blocked else ""))
            t.append(f" {g.per_point.get(label, 0)}")
        t.append("\n")
    else:
        for label in ctl.labels:
            mark = "▶ " if label == g.next_point else ("✗ " if label in g.blocked else "  ")
            t.append(f"{mark}{label}", style="bold magenta" if label == ctl.point else "")
            target = ctl.targets.get(label)
            if target is not None:
                x, y, z = target.position * 1e3
                t.append(f" {target.kind:<6} [{x:.0f}, {y:.0f}, {z:.0f}] mm", style="dim")
            k = g.per_point.get(label, 0)
            t.append(f"  {k} sample{'s' if k != 1 else ''}")
            if label in g.blocked:
                t.append(f"  not offered: {g.blocked[label]}", style="yellow")
            t.append("\n")
    if g.next_point is not None:
        t.append(f"next: {g.next_point}" if compact else f"next: touch {g.next_point}", style="bold")
        t.append(" (fewest samples; vary the orientation)\n" if not compact else "  ", style="dim")
    elif ctl.guided and g.blocked and len(g.blocked) == len(ctl.labels):
        t.append("no point this arm can be sent to: check the cell file\n", style="bold yellow")
    t.append(f"{g.taken}/{g.needed if g.needed is not None else '?'} samples" if compact else
             f"samples {g.taken} / {g.needed if g.needed is not None else '?'} needed")
    t.append("  ")
    t.append(f" {g.status.upper() if g.status != 'waiting' else 'waiting'} ", style=GUIDE_COLOURS.get(g.status, "dim"))
    if g.status == "NO LIMITS":
        t.append(f"\nno limits for {ctl.model.name}/{ctl.judged_as}: the session cannot PASS" +
                 ("" if compact else " (--judge PROCEDURE to use a procedure's limits)"), style="dim")
    if compact:
        marks = [("✓ " if c.ok else "✗ ") + SHORT.get(c.name, c.name) for c in g.checks
                 if c.ok is not None and c.name != "samples"]
        if marks:
            t.append("\n" + " ".join(marks), style="dim")
        return t
    for c in g.checks:
        sym = "·" if c.ok is None else ("✓" if c.ok else "✗")
        t.append(f"\n {sym} {c.name}: {c.text}", style="" if c.ok is None else ("green" if c.ok else "yellow"))
    return t


def solve_text(ctl: JogController, compact: bool) -> Text:
    st = ctl.solve_state
    t = Text()
    if st.status == "waiting":
        t.append("record samples to start the solve", style="dim")
        return t
    t.append(f"{st.n_samples} sample{'s' if st.n_samples != 1 else ''} · ")
    if st.status == "error":
        need = re.search(r"need at least (\d+) samples", st.message)
        if compact and need:  # the solver's sentence does not fit a 40-column half
            t.append(f"too few: need at least {need.group(1)}", style="bold yellow")
        else:
            t.append(st.message, style="bold yellow")
        return t
    res = st.residuals
    before, after, mx = (res.get(k) for k in ("rms_before_m", "rms_after_m", "max_after_m"))

    def um(v):
        return "–" if v is None else f"{v * 1e6:.1f}"

    if compact:
        t.append(f"RMS {um(before)} → {um(after)} µm, max {um(mx)}\n")
    else:
        t.append(f"{st.message} · residual RMS {um(before)} → {um(after)} µm, max {um(mx)} µm\n")
    warning = st.warning
    if warning:
        t.append(f"⚠ {warning}\n", style="bold black on yellow")
    if st.identified_ok:
        t.append("identified", style="bold green")
        t.append(" (correction ± std):\n")
    else:
        t.append("fitted, NOT identified", style="bold yellow")
        t.append(" (correction ± std):\n")
    value_style = "" if st.identified_ok else "dim"
    for name, value, std, unit in st.identified:
        u, k = human_of(unit)
        sd = "" if std is None else f" ± {std * k:.4f}"
        t.append(f"  {name:<14}{value * k:+10.4f}{sd} {u}\n", style=value_style)
    if st.unidentifiable:
        t.append("not identifiable — add poses that change these:\n", style="bold yellow")
        for name, reason in st.unidentifiable.items():
            t.append(f"  {name}: ", style="yellow")
            t.append(f"{reason}\n")
    else:
        t.append("every requested parameter is identifiable\n", style="green")
    t.rstrip()
    return t


def sample_cells(ctl: JogController, sample, compact: bool) -> list:
    """One row of the samples table: number, point, touch (forced stands out), residual after the live solve,
    and (wide) the joints."""
    from station.tui.livesolve import is_forced

    touch = sample.status.get("touch")
    if is_forced(sample):
        cell = Text("! forced", style="bold black on yellow")
    elif touch is None:
        cell = Text("–", style="dim")
    else:
        cell = Text("● yes" if touch else "○ no", style="green" if touch else "")
    res = ctl.solve_state.sample_residuals.get(sample.seq)
    row = [str(ctl.number(sample)), sample.point, cell, "" if res is None else f"{res * 1e6:.1f}"]
    if not compact:
        row += [f"{v * human(joint_quantity(j.revolute))[1]:.3f}" for v, j in zip(sample.q, ctl.model.joints,
                                                                                      strict=True)]
    return row


def sample_columns(ctl: JogController, compact: bool) -> list[str]:
    cols = ["#", "point", "touch", "res µm"]
    return cols if compact else cols + [f"J{i + 1}" for i in range(ctl.model.n_joints)]
