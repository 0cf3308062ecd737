"""``station jog``: the technician's terminal UI (textual). Widgets render a ``JogController``. Moves are started
without waiting, so the UI thread is never blocked by motion and the stop key is always served at once."""

from __future__ import annotations

import asyncio
import contextlib
import signal
import threading

import numpy as np
from rich.text import Text
from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.css.query import NoMatches
from textual.screen import ModalScreen
from textual.widgets import Button, DataTable, Footer, Header, Static

from station.tui.controller import HOLD_CHECK_S, STEP_PRESETS, ExportPlan, JogController, WritebackPlan
from station.units import human, human_of, joint_quantity

# (plus key, minus key) per axis: J1..J6 in joint mode, X Y Z Rx Ry Rz in Cartesian mode
JOG_KEYS = (("q", "a"), ("w", "s"), ("e", "d"), ("r", "f"), ("t", "g"), ("y", "h"), ("u", "j"))
POLL_S = 0.2


def _fmt_value(v: float, rotational: bool) -> str:
    unit, k = human(joint_quantity(rotational))
    return f"{v * k:+10.3f} {unit:<3}"


class SamplesTable(DataTable):
    """The samples list never takes focus (a focused DataTable swallows enter and the arrow keys in a real
    terminal); the app's bindings move its cursor."""

    can_focus = False


class ConfirmScreen(ModalScreen[bool]):
    """A yes/no question (discard a sample); enter does not confirm (it is the record key)."""

    BINDINGS = [Binding("y", "confirm", "yes"), Binding("n,escape", "cancel", "no")]
    AUTO_FOCUS = "#cf-no"
    DEFAULT_CSS = """
    ConfirmScreen { align: center middle; }
    #cf-box { width: 70; height: auto; border: thick $warning; background: $surface; padding: 1 2; }
    #cf-buttons { height: auto; margin-top: 1; }
    #cf-buttons Button { margin-right: 2; }
    """

    def __init__(self, question: str, yes: str = "Yes (y)") -> None:
        super().__init__()
        self.question, self.yes = question, yes

    def compose(self) -> ComposeResult:
        with Vertical(id="cf-box"):
            yield Static(Text(self.question, style="bold"), id="cf-question")
            with Horizontal(id="cf-buttons"):
                yield Button(self.yes, variant="error", id="cf-yes")
                yield Button("No (n)", variant="primary", id="cf-no")

    def on_button_pressed(self, event: Button.Pressed) -> None:
        self.dismiss(event.button.id == "cf-yes")

    def action_confirm(self) -> None:
        self.dismiss(True)

    def action_cancel(self) -> None:
        self.dismiss(False)


def export_question(plan: ExportPlan) -> str:
    return (f"Export the calibration for the controller?\n\nThe controller keeps its own calibration: nothing is "
            f"written to the robot, it stays unchanged. Files (calibration.conf, URDF, YAML) go to\n  {plan.folder}\n"
            "for the integrator to install.")


class WritebackScreen(ModalScreen[bool]):
    """Explicit confirmation with the before/after of every value the write would change."""

    BINDINGS = [Binding("y", "confirm", "write to robot"), Binding("n,escape", "cancel", "cancel")]
    AUTO_FOCUS = "#wb-no"  # enter (the record key) must never confirm a write by accident
    DEFAULT_CSS = """
    WritebackScreen { align: center middle; }
    #wb-box { width: 90; height: auto; border: thick $warning; background: $surface; padding: 1 2; }
    #wb-buttons { height: auto; margin-top: 1; }
    #wb-buttons Button { margin-right: 2; }
    """

    def __init__(self, plan: WritebackPlan) -> None:
        super().__init__()
        self.plan = plan

    def compose(self) -> ComposeResult:
        t = Text()
        if self.plan.kind == "restore":
            t.append("Restore the calibration the robot had before this session's write-back?\n\n", style="bold")
        else:
            t.append("Write joint zero offsets to the robot?\n\n", style="bold")
        t.append(f"{'parameter':<12}{'before [deg]':>16}{'correction':>14}{'after [deg]':>16}\n", style="bold")
        for name in sorted(self.plan.after, key=lambda n: (len(n), n)):
            b = self.plan.before.get(name, 0.0)
            a = self.plan.after[name]
            c = self.plan.corrections.get(name)
            mark = "" if c is None else f"{np.rad2deg(c):+14.4f}"
            t.append(f"{name:<12}{np.rad2deg(b):+16.4f}{mark:>14}{np.rad2deg(a):+16.4f}\n",
                     style="bold yellow" if c is not None or a != b else "")
        if self.plan.kind == "restore":
            t.append("\nThe values come from this session's pre-image (calibration-backup.json).\n")
        else:
            t.append("\nThe pre-image is journaled and saved as calibration-backup.json before writing.\n")
        with Vertical(id="wb-box"):
            yield Static(t, id="wb-table")
            with Horizontal(id="wb-buttons"):
                yield Button("Write (y)", variant="error", id="wb-yes")
                yield Button("Cancel (n)", variant="primary", id="wb-no")

    def on_button_pressed(self, event: Button.Pressed) -> None:
        self.dismiss(event.button.id == "wb-yes")

    def action_confirm(self) -> None:
        self.dismiss(True)

    def action_cancel(self) -> None:
        self.dismiss(False)


class JogApp(App):
    TITLE = "station jog"
    AUTO_FOCUS = None  # nothing takes focus: every key reaches the app's bindings
    CSS = """
    #banner { display: none; background: $error; color: $text; text-style: bold; padding: 0 1; height: auto; }
    #banner.on { display: block; }
    #left { width: 60; }
    #right { width: 1fr; }
    .panel { border: round $primary; padding: 0 1; height: auto; }
    #samples { height: 1fr; min-height: 6; border: round $primary; }
    #solve { height: auto; max-height: 24; }
    #message { height: 1; padding: 0 1; background: $boost; }
    """
    BINDINGS = [
        Binding("space", "stop", "STOP", priority=True),
        Binding("x", "stop", "STOP", show=False, priority=True),
        Binding("m", "toggle_mode", "joint/cart"),
        Binding("o", "toggle_frame", "base/tool", show=False),
        Binding("1", "step(0)", f"{STEP_PRESETS[0]:g}", show=False),
        Binding("2", "step(1)", f"{STEP_PRESETS[1]:g}", show=False),
        Binding("3", "step(2)", f"{STEP_PRESETS[2]:g}", show=False),
        Binding("4", "step(3)", f"{STEP_PRESETS[3]:g}", show=False),
        Binding("0", "hold_mode", "hold-to-run", show=False),
        Binding("minus", "speed(-1)", "slower", show=False),
        Binding("plus,equals_sign", "speed(1)", "faster", show=False),
        Binding("p", "point(1)", "point"),
        Binding("P", "point(-1)", "previous point", show=False),
        Binding("enter", "record", "record"),
        Binding("exclamation_mark", "record_forced", "record w/o contact", show=False),
        Binding("k", "retake", "retake"),
        Binding("delete,backspace", "discard", "discard"),
        Binding("up", "select(-1)", "select", show=False),
        Binding("down", "select(1)", "select", show=False),
        Binding("c", "enable", "clear fault", show=False),
        Binding("W", "writeback", "write back"),
        Binding("ctrl+q", "quit", "quit"),
    ]

    def __init__(self, controller: JogController, *, poll_s: float = POLL_S) -> None:
        super().__init__()
        self.ctl = controller
        self.poll_s = poll_s
        self._timer = None
        from station.tui.keys import KeyArrivals

        self._shown: dict[str, object] = {}  # what each panel shows (refresh_view skips unchanged panels)
        self.key_arrivals = KeyArrivals()  # fed by the terminal input thread (JogDriver), read by hold-to-run
        self.interrupted: int | None = None  # the signal that ended the app (SIGTERM/SIGINT), if any
        self._old_handlers: dict = {}
        n = controller.model.n_joints
        for i, (plus, minus) in enumerate(JOG_KEYS[:max(n, 6)]):
            self._bindings.bind(plus, f"jog({i},1)", show=False)
            self._bindings.bind(minus, f"jog({i},-1)", show=False)

    # ---- layout ----------------------------------------------------------------------------------------
    def compose(self) -> ComposeResult:
        yield Header()
        yield Static("", id="banner")
        with Horizontal():
            with Vertical(id="left"):
                yield Static(id="joints", classes="panel")
                yield Static(id="tcp", classes="panel")
                yield Static(id="jog", classes="panel")
                yield Static(id="keys", classes="panel")
            with Vertical(id="right"):
                yield Static(id="guide", classes="panel")
                yield SamplesTable(id="samples", cursor_type="row", zebra_stripes=True)
                yield Static(id="solve", classes="panel")
        yield Static("", id="message")
        yield Footer()

    def on_mount(self) -> None:
        ident = self.ctl.session.session_id
        self.sub_title = f"{self.ctl.model.name} · session {ident}"
        self.query_one("#joints").border_title = "joints (as the device reports them)"
        self.query_one("#tcp").border_title = "TCP (nominal model FK, base frame)"
        self.query_one("#jog").border_title = "jog"
        self.query_one("#keys").border_title = "keys"
        self.query_one("#solve").border_title = f"live solve: {self.ctl.identify}"
        self.query_one("#guide").border_title = "guidance"
        self.query_one("#tcp").border_title = ("TCP (nominal model FK, base frame; rotation vector as on the "
                                               "UR pendant)" if self.ctl.ur_rotvec else
                                               "TCP (nominal model FK, base frame; roll-pitch-yaw)")
        table = self.query_one("#samples", DataTable)
        table.border_title = f"samples → {self.ctl.session.samples_csv}"
        table.add_columns("#", "point", "touch", *[f"J{i + 1}" for i in range(self.ctl.model.n_joints)])
        self.query_one("#keys", Static).update(self._keys_text())
        r = self.ctl.poll(block=True)
        if r is not None and not r.enabled and not self.ctl.fault:
            self.ctl.message = "robot disabled (torque off): press c to enable"
        self.refresh_view()
        self._catch_signals()
        self.ctl.key_arrivals = self._key_arrivals
        self._timer = self.set_interval(self.poll_s, self._tick)
        self._hold_timer = self.set_interval(HOLD_CHECK_S, self._hold_tick)

    def _keys_text(self) -> Text:
        n = max(self.ctl.model.n_joints, 6)
        pairs = " ".join(f"{p}/{m}" for p, m in JOG_KEYS[:n])
        return Text.from_markup(
            f"[b]{pairs}[/b] axis 1..{n} +/-\n[b]m[/b] joint|Cart  [b]o[/b] base|tool frame  [b]- +[/b] speed %\n"
            f"[b]1 2 3 4[/b] step {' / '.join(f'{s:g}' for s in STEP_PRESETS)} mm|deg  [b]0[/b] hold-to-run\n"
            "[b]p[/b] point  [b]enter[/b] record  [b]![/b] record w/o contact\n"
            "[b]↑ ↓[/b] select  [b]k[/b] retake  [b]del[/b] discard  [b]W[/b] write\n"
            "[b][reverse] space [/reverse][/b] STOP (x)  [b]c[/b] clear fault  [b]ctrl+q[/b] quit")

    def _catch_signals(self) -> None:
        """SIGTERM and SIGINT quit like ctrl+q (stop, journal the end, store): the handler only schedules the
        quit on the event loop. Inside a write-back the engine holds both (station.engine.writeback
        .signals_held) and delivers them here once the device is written and read back."""
        if threading.current_thread() is not threading.main_thread():
            return
        loop = asyncio.get_running_loop()

        def quit_on(signum, frame) -> None:
            self.interrupted = signum
            loop.call_soon_threadsafe(self.exit)

        for sig in (signal.SIGTERM, signal.SIGINT):
            with contextlib.suppress(ValueError, OSError):
                self._old_handlers[sig] = signal.signal(sig, quit_on)

    def get_driver_class(self):
        """Textual's driver, on Linux/macOS the one that asks the terminal for key releases (station.tui.keys)."""
        cls = super().get_driver_class()
        try:
            from textual.drivers.linux_driver import LinuxDriver

            from station.tui.keys import JogDriver
        except ImportError:  # no termios (Windows): repeats only
            return cls
        return JogDriver if cls is LinuxDriver else cls

    def on_key(self, event) -> None:
        """A key release (kitty keyboard protocol, station.tui.keys): a released jog key ends its hold."""
        from station.tui.keys import RELEASED

        if not event.key.startswith(RELEASED):
            return
        event.stop()
        key = event.key[len(RELEASED):]
        for i, (plus, minus) in enumerate(JOG_KEYS):
            if key in (plus, minus):
                self.ctl.release(i, 1 if key == plus else -1)  # (already stopped on the input thread, mostly)
                self.refresh_view()
                return

    def key_released(self, key: str) -> None:
        """On the terminal's input thread (station.tui.keys): a jog key's release stops its hold at once, not
        after the key events queued before it (JogController.release is safe from this thread)."""
        if self.ctl.closed:
            return
        for i, (plus, minus) in enumerate(JOG_KEYS):
            if key in (plus, minus):
                self.ctl.release(i, 1 if key == plus else -1)
                return

    def _key_arrivals(self, axis: int, direction: int, count: int) -> tuple[int, list[float]]:
        """Arrival times of a jog key at the terminal input thread (station.tui.keys.JogDriver)."""
        plus, minus = JOG_KEYS[axis]
        return self.key_arrivals.since(plus if direction > 0 else minus, count)

    def _hold_tick(self) -> None:
        if self.ctl.closed:
            return
        if self.ctl.hold_state is None:
            self.ctl.hold_idle()
            return
        self.ctl.hold_tick()
        if self.ctl.hold_state is None:
            with contextlib.suppress(NoMatches):
                self.refresh_view()

    # ---- periodic refresh ------------------------------------------------------------------------------
    def _tick(self) -> None:
        if self.ctl.closed:
            return
        self.ctl.poll()
        with contextlib.suppress(NoMatches):  # a tick racing the app's shutdown: the widgets are already gone
            self.refresh_view()

    def refresh_view(self) -> None:
        ctl = self.ctl
        banner = self.query_one("#banner", Static)
        if ctl.fault:
            banner.update(f"⚠ FAULT — motion stopped: {ctl.fault}   (c: clear fault and re-enable)")
            banner.add_class("on")
        else:
            banner.remove_class("on")
        r = ctl.readout
        joints = Text()
        if r is not None:
            for i, j in enumerate(ctl.model.joints):
                style = "bold" if ctl.mode == "joint" and i == ctl.axis else ""
                joints.append(f"J{i + 1} {j.name[:8]:<8}{_fmt_value(r.q[i], j.revolute)}", style=style)
                lo, hi = (np.rad2deg([j.lower, j.upper]) if j.revolute else np.array([j.lower, j.upper]) * 1e3)
                joints.append(f"  [{lo:.0f}, {hi:.0f}]\n", style="dim")
        self._show("#joints", joints)
        tcp = Text()
        if r is not None:
            x, y, z = r.tcp[:3] * 1e3
            if ctl.ur_rotvec:  # as the UR pendant shows it: rotation vector in rad
                rx, ry, rz = r.tcp[3:]
                u = "rad"
            else:
                rx, ry, rz = np.rad2deg(r.tcp[3:])
                u = "deg"
            tcp.append(f"X {x:+10.3f} mm   Rx {rx:+9.4f} {u}\nY {y:+10.3f} mm   Ry {ry:+9.4f} {u}\n"
                       f"Z {z:+10.3f} mm   Rz {rz:+9.4f} {u}")
        self._show("#tcp", tcp)
        jog = Text()
        jog.append("mode  ")
        jog.append(f"{ctl.mode:<10}", style="bold cyan")
        if ctl.mode == "cartesian":
            jog.append(f"{ctl.frame} frame  ", style="bold cyan")
        jog.append("step  " if not ctl.continuous else "")
        jog.append("hold-to-run\n" if ctl.continuous else f"{ctl.step:g} mm | deg\n", style="bold cyan")
        jog.append("speed ")
        jog.append(f"{ctl.speed_percent} % = {ctl.speed_mm_s:g} mm/s", style="bold cyan")
        jog.append(" (max 250)  point ")
        jog.append(f"{ctl.point}\n", style="bold magenta")
        jog.append("touch ")
        if ctl.stale:
            jog.append(" ? no reading ", style="reverse red")
        elif r is None or r.touch is None:
            jog.append(" no contact input ", style="reverse dim")
        elif r.touch:
            jog.append(" ● CONTACT ", style="bold black on green")
        else:
            jog.append(" ○ no contact ", style="dim")
        state = "no reading" if ctl.stale else ("moving" if r and r.moving else "still")
        jog.append(f"   {state}", style="green" if state == "still" else "yellow")
        if r is not None and not r.enabled:
            jog.append("  disabled", style="red")
        self._show("#jog", jog)
        self._refresh_samples()
        self._show("#guide", self._guide_text())
        self._show("#solve", self._solve_text())
        self._show("#message", ctl.message)

    def _show(self, selector: str, content) -> None:
        """Update a panel only when its content changed: every update re-lays out the screen, and doing it for
        all panels at each poll kept the UI thread busy enough to delay hold-to-run on a loaded host."""
        if self._shown.get(selector) == content:
            return
        self.query_one(selector, Static).update(content)
        self._shown[selector] = content.copy() if isinstance(content, Text) else content

    def _refresh_samples(self) -> None:
        table = self.query_one("#samples", DataTable)
        samples = self.ctl.session.samples
        key = (tuple((s.seq, s.point, s.status.get("touch"), self.ctl.number(s)) for s in samples), self.ctl.selected)
        if key == self._shown.get("#samples"):
            return
        self._shown["#samples"] = key
        table.clear()
        for s in samples:
            touch = s.status.get("touch")
            touch = "–" if touch is None else ("●" if touch else "○")
            vals = [f"{v * human(joint_quantity(j.revolute))[1]:.3f}"
                    for v, j in zip(s.q, self.ctl.model.joints, strict=True)]
            table.add_row(str(self.ctl.number(s)), s.point, touch, *vals)
        if samples:
            sel = len(samples) - 1 if self.ctl.selected is None else self.ctl.selected
            table.move_cursor(row=sel, animate=False)

    def _guide_text(self) -> Text:
        ctl, g = self.ctl, self.ctl.guide
        t = Text()
        pts = ctl.cell.points if ctl.cell is not None else {}
        for label in ctl.labels:
            mark = "▶ " if label == g.next_point else "  "
            style = "bold magenta" if label == ctl.point else ""
            t.append(f"{mark}{label}", style=style)
            p = pts.get(label)
            if p is not None:
                x, y, z = p.position * 1e3
                t.append(f" {p.kind:<6} [{x:.0f}, {y:.0f}, {z:.0f}] mm", style="dim")
            elif isinstance(ctl.reference, dict) and label in ctl.reference:
                x, y, z = ctl.reference[label] * 1e3
                t.append(f" ref    [{x:.0f}, {y:.0f}, {z:.0f}] mm", style="dim")
            t.append(f"  {g.per_point.get(label, 0)} samples\n")
        if g.next_point is not None:
            t.append(f"next: touch {g.next_point}", style="bold")
            t.append(" (fewest samples; vary the orientation)\n", style="dim")
        t.append(f"samples {g.taken} / {g.needed if g.needed is not None else '?'} needed   ")
        colour = {"good enough": "bold black on green", "not yet": "bold yellow", "NO LIMITS": "bold white on magenta"}
        t.append(f" {g.status.upper() if g.status != 'waiting' else 'waiting'} ", style=colour.get(g.status, "dim"))
        if g.status == "NO LIMITS":
            t.append(f"\nno limits for {ctl.model.name}/{ctl.judged_as}: the session cannot PASS "
                     "(--judge PROCEDURE to use a procedure's limits)", style="dim")
        for c in g.checks:
            sym = "·" if c.ok is None else ("✓" if c.ok else "✗")
            t.append(f"\n {sym} {c.name}: {c.text}", style="" if c.ok is None else ("green" if c.ok else "yellow"))
        return t

    def _solve_text(self) -> Text:
        st = self.ctl.solve_state
        t = Text()
        if st.status == "waiting":
            t.append("record samples to start the solve", style="dim")
            return t
        t.append(f"{st.n_samples} samples · ")
        if st.status == "error":
            t.append(st.message, style="bold yellow")
            return t
        res = st.residuals
        before, after, mx = (res.get(k) for k in ("rms_before_m", "rms_after_m", "max_after_m"))

        def um(v):
            return "–" if v is None else f"{v * 1e6:.1f}"

        t.append(f"{st.message} · residual RMS {um(before)} → {um(after)} µm, max {um(mx)} µm\n")
        t.append("identified", style="bold green")
        t.append(" (correction ± std):\n")
        for name, value, std, unit in st.identified:
            u, k = human_of(unit)
            sd = "" if std is None else f" ± {std * k:.4f}"
            t.append(f"  {name:<14}{value * k:+10.4f}{sd} {u}\n")
        if st.unidentifiable:
            t.append("not identifiable — add poses that change these:\n", style="bold yellow")
            for name, reason in st.unidentifiable.items():
                t.append(f"  {name}: ", style="yellow")
                t.append(f"{reason}\n")
        else:
            t.append("every requested parameter is identifiable\n", style="green")
        return t

    # ---- actions ---------------------------------------------------------------------------------------
    def check_action(self, action: str, parameters: tuple) -> bool | None:
        """While a dialog is open only STOP and quit reach the app (no jog or record behind the dialog)."""
        return len(self.screen_stack) <= 1 or action in ("stop", "quit")

    def action_stop(self) -> None:
        self.ctl.stop()
        self.refresh_view()

    def action_jog(self, axis: int, direction: int) -> None:
        if self.ctl.continuous:
            # hold-to-run: a repeat only keeps the hold alive; the UI's time belongs to the re-commands and
            # the release check (the 200 ms poll refreshes the view)
            held = self.ctl.hold_state is not None
            self.ctl.jog(axis, direction)
            if not held:
                self.refresh_view()
            return
        self.ctl.jog(axis, direction)
        self.ctl.poll(block=True)
        self.refresh_view()

    def action_toggle_frame(self) -> None:
        self.ctl.toggle_frame()
        self.refresh_view()

    def action_hold_mode(self) -> None:
        self.ctl.set_continuous()
        self.refresh_view()

    def action_toggle_mode(self) -> None:
        self.ctl.toggle_mode()
        self.refresh_view()

    def action_step(self, index: int) -> None:
        self.ctl.set_step(index)
        self.refresh_view()

    def action_speed(self, delta: int) -> None:
        self.ctl.change_speed(delta)
        self.refresh_view()

    def action_point(self, delta: int) -> None:
        self.ctl.next_point(delta)
        self.refresh_view()

    def action_record(self) -> None:
        self.ctl.record()
        self.refresh_view()

    def action_record_forced(self) -> None:
        self.ctl.record(force=True)
        self.refresh_view()

    def action_retake(self) -> None:
        self.ctl.retake()
        self.refresh_view()

    def action_discard(self) -> None:
        sample = self.ctl.selected_sample()
        if sample is None:
            self.ctl.message = "nothing to discard"
            self.refresh_view()
            return
        n = self.ctl.number(sample)

        def done(confirmed: bool | None) -> None:
            if confirmed and self.ctl.selected_sample() is sample:
                self.ctl.discard()
            else:
                self.ctl.message = f"kept #{n}"
            self.refresh_view()

        self.push_screen(ConfirmScreen(f"Discard sample #{n} on {sample.point}? It stays in the journal as "
                                       "discarded.", yes="Discard (y)"), done)

    def action_select(self, delta: int) -> None:
        self.ctl.select(delta)
        self.refresh_view()

    def action_enable(self) -> None:
        self.ctl.enable()
        self.refresh_view()

    def action_writeback(self) -> None:
        plan = self.ctl.writeback_plan()
        self.refresh_view()
        if plan is None:
            return

        def done(confirmed: bool | None) -> None:
            if confirmed:
                self.ctl.writeback_apply(plan)
            else:
                self.ctl.message = "write-back cancelled: nothing written"
            self.refresh_view()

        if isinstance(plan, ExportPlan):
            self.push_screen(ConfirmScreen(export_question(plan), yes="Export (y)"), done)
        else:
            self.push_screen(WritebackScreen(plan), done)

    def on_unmount(self) -> None:
        if self._timer is not None:
            self._timer.stop()
            self._hold_timer.stop()
        self.ctl.close()
        for sig, handler in self._old_handlers.items():
            signal.signal(sig, handler)
