"""``station jog``: the technician's terminal UI (textual). Widgets render a ``JogController`` (panel texts:
``station.tui.panels``; dialogs: ``station.tui.dialogs``). Moves are started without waiting, so the UI thread
is never blocked by motion, and the STOP keys (space, x, ctrl+c) act on the terminal's input thread as soon as
they are typed, ahead of everything queued for the UI.

Layout: two columns. Below ``WIDE_MIN`` columns (or too few rows for the keys panel) the panels switch to
their compact forms, which fit an 80x24 terminal whole; below 80x24 a notice says the terminal is too small
(the keys still work). The bottom line is the station's own key help, not textual's footer."""

from __future__ import annotations

import asyncio
import contextlib
import signal
import threading

from rich.text import Text
from textual import events
from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical, VerticalScroll
from textual.css.query import NoMatches
from textual.widgets import DataTable, Static

from station.tui import panels
from station.tui.controller import HOLD_CHECK_S, ExportPlan, JogController
from station.tui.dialogs import (  # noqa: F401  (importable from here as before)
    ConfirmScreen,
    HelpScreen,
    NearScreen,
    QuitScreen,
    WritebackScreen,
    export_question,
    near_question,
    quit_question,
)
from station.tui.panels import JOG_KEYS, NEAR_KEY, SEAT_KEY

POLL_S = 0.2
MIN_SIZE = (80, 24)  # the smallest terminal every panel fits into (compact forms)
WIDE_MIN = 120  # columns for the wide forms and the keys panel
STOP_KEYS = ("space", "x", "ctrl+c")


class SamplesTable(DataTable):
    """The samples list never takes focus (a focused DataTable swallows enter and the arrow keys in a real
    terminal); the app's bindings move its cursor."""

    can_focus = False


class SolveScroll(VerticalScroll):
    """The live solve scrolls (PgUp/PgDn) without taking focus."""

    can_focus = False


class JogApp(App):
    TITLE = "station jog"
    AUTO_FOCUS = None  # nothing takes focus: every key reaches the app's bindings
    ENABLE_COMMAND_PALETTE = False  # no framework chrome: the keys are the station's
    CSS = """
    #title { height: 1; padding: 0 0; }
    #banner { display: none; background: $error; color: $text; text-style: bold; padding: 0 1; height: auto; }
    #banner.on { display: block; }
    #toosmall { display: none; background: $warning; color: $text; text-style: bold; padding: 0 1; height: auto; }
    #toosmall.on { display: block; }
    #main { height: 1fr; }
    #left { width: 60; }
    #right { width: 1fr; }
    .panel { border: round $primary; padding: 0 1; height: auto; }
    #keys { height: auto; }
    #samples { height: 1fr; min-height: 5; border: round $primary; }
    #solve-box { height: auto; max-height: 60%; border: round $primary; padding: 0 1; }
    #solve { height: auto; }
    #message { height: auto; max-height: 2; padding: 0 1; background: $boost; }
    #help { height: 1; padding: 0 0; }
    #main.-compact #left { width: 1fr; }
    #main.-small #left { overflow-y: auto; }
    #main.-small #right { overflow-y: auto; }
    #main.-compact #keys { height: 1fr; min-height: 3; }
    #main.-compact #samples { min-height: 4; }
    #main.-compact #solve-box { height: 1fr; max-height: 100%; min-height: 4; }
    """
    BINDINGS = [
        Binding("space", "stop", "STOP", priority=True),
        Binding("x", "stop", "STOP", show=False, priority=True),
        Binding("ctrl+c", "stop('ctrl+c')", "STOP", show=False, priority=True),
        Binding("m", "toggle_mode", "joint/cart"),
        Binding("o", "toggle_frame", "base/tool", show=False),
        Binding("1", "step(0)", show=False),
        Binding("2", "step(1)", show=False),
        Binding("3", "step(2)", show=False),
        Binding("4", "step(3)", show=False),
        Binding("0", "hold_mode", "hold-to-run", show=False),
        Binding("minus", "speed(-1)", "slower", show=False),
        Binding("plus,equals_sign", "speed(1)", "faster", show=False),
        Binding("p", "point(1)", "point"),
        Binding("P", "point(-1)", "previous point", show=False),
        Binding(NEAR_KEY, "near", "go near"),
        Binding(SEAT_KEY, "seat", "seat"),
        Binding("enter", "record", "record"),
        Binding("exclamation_mark", "record_forced", "record w/o contact", show=False),
        Binding("k", "retake", "retake"),
        Binding("delete,backspace", "discard", "discard"),
        Binding("up", "select(-1)", "select", show=False),
        Binding("down", "select(1)", "select", show=False),
        Binding("pageup", "scroll_solve(-1)", show=False),
        Binding("pagedown", "scroll_solve(1)", show=False),
        Binding("question_mark", "help", "keys", show=False),
        Binding("c", "enable", "clear fault", show=False),
        Binding("W", "writeback", "write back"),
        Binding("ctrl+q", "quit", "quit", priority=True),
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
        self._key_time = 0.0  # when the key being handled arrived (textual's monotonic clock)
        self.compact = False
        self.too_small = False
        n = controller.model.n_joints
        for i, (plus, minus) in enumerate(JOG_KEYS[:max(n, 6)]):
            self._bindings.bind(plus, f"jog({i},1)", show=False)
            self._bindings.bind(minus, f"jog({i},-1)", show=False)

    # ---- layout ----------------------------------------------------------------------------------------
    def compose(self) -> ComposeResult:
        yield Static("", id="title")
        yield Static("", id="banner")
        yield Static("", id="toosmall")
        with Horizontal(id="main"):
            with Vertical(id="left"):
                yield Static(id="joints", classes="panel")
                yield Static(id="tcp", classes="panel")
                yield Static(id="jog", classes="panel")
                yield Static(id="keys", classes="panel")
            with Vertical(id="right"):
                yield Static(id="guide", classes="panel")
                yield SamplesTable(id="samples", cursor_type="row", zebra_stripes=True)
                with SolveScroll(id="solve-box"):
                    yield Static(id="solve")
        yield Static("", id="message")
        yield Static("", id="help")

    def on_mount(self) -> None:
        self.query_one("#keys").border_title = "keys"
        self.query_one("#solve-box").border_title = f"live solve: {self.ctl.identify}"
        self.query_one("#guide").border_title = "guidance"
        self._apply_layout(self.size.width, self.size.height)
        r = self.ctl.poll(block=True)
        if r is not None and not r.enabled and not self.ctl.fault:
            self.ctl.message = "robot disabled (torque off): press c to enable"
        self.refresh_view()
        self._catch_signals()
        self.ctl.key_arrivals = self._key_arrivals
        self._timer = self.set_interval(self.poll_s, self._tick)
        self._hold_timer = self.set_interval(HOLD_CHECK_S, self._hold_tick)

    def on_resize(self, event: events.Resize) -> None:
        self._apply_layout(event.size.width, event.size.height)
        with contextlib.suppress(NoMatches):
            self.refresh_view()

    def _apply_layout(self, width: int, height: int) -> None:
        """Wide or compact panels by the terminal's size; a notice below MIN_SIZE."""
        n = self.ctl.model.n_joints
        compact = width < WIDE_MIN or height < 27 + n  # the wide left column needs 27 + n rows
        small = width < MIN_SIZE[0] or height < MIN_SIZE[1]
        with contextlib.suppress(NoMatches):
            self.query_one("#main").set_class(compact, "-compact")
            notice = self.query_one("#toosmall", Static)
            notice.set_class(small, "on")
            self.query_one("#main").set_class(small, "-small")
            notice.update(f"terminal {width}x{height} is too small (needs {MIN_SIZE[0]}x{MIN_SIZE[1]}): panels are "
                          "cut; STOP and quit still work" if small else "")
            self.query_one("#tcp").border_title = panels.tcp_title(self.ctl, compact)
            self.query_one("#joints").border_title = "joints" if compact else "joints (as the device reports them)"
            self.query_one("#jog").border_title = "jog" if compact else "jog · distances in the nominal model"
            samples = self.query_one("#samples", DataTable)
            samples.border_title = ("samples" if compact else f"samples → {self.ctl.session.samples_csv}")
            if compact != self.compact or not samples.columns:
                samples.clear(columns=True)
                samples.add_columns(*panels.sample_columns(self.ctl, compact))
                self._shown.pop("#samples", None)
        self.compact, self.too_small = compact, small

    def _catch_signals(self) -> None:
        """SIGTERM and SIGINT quit like a confirmed ctrl+q (stop, journal the end, store): the handler only
        schedules the quit on the event loop. Inside a write-back the engine holds both (station.engine.writeback
        .signals_held) and delivers them here once the device is written and read back. (Ctrl+C typed in the
        terminal is a key, not a signal: it stops the robot and the UI stays.)"""
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

    # ---- keys as they arrive ------------------------------------------------------------------------------
    async def on_event(self, event: events.Event) -> None:
        if isinstance(event, events.Key):
            self._key_time = event.time  # set where the terminal's bytes were parsed
        await super().on_event(event)

    def key_pressed(self, key: str) -> None:
        """On the terminal's input thread (station.tui.keys), for every key as soon as it is parsed: a STOP key
        stops the robot here, not after the key events queued before it."""
        if key in STOP_KEYS and not self.ctl.closed:
            self.ctl.stop_now()

    def _stale_key(self) -> bool:
        """The key being handled arrived before the last STOP: it must not start motion after it."""
        return self._key_time < self.ctl.stop_mark

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
        ctl, compact = self.ctl, self.compact
        banner = self.query_one("#banner", Static)
        if ctl.fault:
            banner.update(f"⚠ FAULT — motion stopped: {ctl.fault}   (c: clear fault and re-enable)")
            banner.add_class("on")
        else:
            banner.remove_class("on")
        self._show("#title", panels.title_text(ctl, compact))
        self._show("#joints", panels.joints_text(ctl, compact))
        self._show("#tcp", panels.tcp_text(ctl, compact))
        self._show("#jog", panels.jog_text(ctl, compact))
        self._show("#keys", panels.keys_text(ctl, compact))
        self._refresh_samples()
        self._show("#guide", panels.guide_text(ctl, compact))
        self._show("#solve", panels.solve_text(ctl, compact))
        self._show("#message", ctl.message)
        self._show("#help", panels.help_line(compact))

    def _show(self, selector: str, content) -> None:
        """Update a panel only when its content changed: every update re-lays out the screen, and doing it for
        all panels at each poll kept the UI thread busy enough to delay hold-to-run on a loaded host."""
        if self._shown.get(selector) == content:
            return
        self.query_one(selector, Static).update(content)
        self._shown[selector] = content.copy() if isinstance(content, Text) else content

    def _refresh_samples(self) -> None:
        table = self.query_one("#samples", DataTable)
        ctl = self.ctl
        samples = ctl.session.samples()
        key = (tuple((s.seq, s.point, s.status.get("touch"), ctl.number(s), ctl.solve_state.sample_residuals.get(
            s.seq)) for s in samples), ctl.selected, self.compact)
        if key == self._shown.get("#samples"):
            return
        self._shown["#samples"] = key
        table.clear()
        for s in samples:
            table.add_row(*panels.sample_cells(ctl, s, self.compact))
        if samples:
            sel = len(samples) - 1 if ctl.selected is None else ctl.selected
            table.move_cursor(row=sel, animate=False)

    # ---- actions ---------------------------------------------------------------------------------------
    def check_action(self, action: str, parameters: tuple) -> bool | None:
        """While a dialog is open only STOP and quit reach the app (no jog or record behind the dialog)."""
        return len(self.screen_stack) <= 1 or action in ("stop", "quit")

    def action_stop(self, key: str = "") -> None:
        # the input thread stopped the robot already when the key came from a terminal (stop_mark after the
        # key's time): stop again (cheap, idempotent) but keep what that stop said; a key that did not pass the
        # input thread (a test's pilot) is stopped here
        first = self.ctl.stop_mark >= self._key_time and self.ctl.message.startswith("STOPPED")
        said = self.ctl.message
        self.ctl.stop_mark = max(self.ctl.stop_mark, self._key_time)
        self.ctl.stop()
        if first:
            self.ctl.message = said
        if key == "ctrl+c" and "quits" not in self.ctl.message:
            self.ctl.message += " (ctrl+c stops; ctrl+q quits)"
        self.refresh_view()

    def action_help_quit(self) -> None:
        """textual binds ctrl+c to a "press ctrl+q to quit" notice; here ctrl+c is STOP."""
        self.action_stop()

    async def action_quit(self) -> None:
        """ctrl+q: quit at once when nothing is at stake, else ask (ctrl+q again or y quits)."""
        if isinstance(self.screen, QuitScreen):
            self.exit()
            return
        concerns = self.ctl.quit_concerns()
        if not concerns:
            self.exit()
            return

        def done(confirmed: bool | None) -> None:
            if confirmed:
                self.exit()
            else:
                self.ctl.message = "not quitting"
                self.refresh_view()

        self.push_screen(QuitScreen(quit_question(concerns), yes="Quit (y)"), done)

    def action_jog(self, axis: int, direction: int) -> None:
        if self._stale_key():
            return  # typed before the STOP, handled after it: no motion
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

    def action_seat(self) -> None:
        self.ctl.toggle_compliant()
        self.ctl.poll(block=True)
        self.refresh_view()

    def action_near(self) -> None:
        if self._stale_key():
            return
        plan = self.ctl.plan_near()
        self.refresh_view()
        if plan is None:
            return
        target = self.ctl.targets[plan.label]

        def done(confirmed: bool | None) -> None:
            if confirmed:
                self.ctl.start_near(plan)
            else:
                self.ctl.message = f"go near {plan.label} cancelled: nothing moved"
            self.refresh_view()

        self.push_screen(NearScreen(plan, near_question(plan, target.kind)), done)

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

    def action_scroll_solve(self, direction: int) -> None:
        box = self.query_one("#solve-box", SolveScroll)
        if direction > 0:
            box.scroll_page_down(animate=False)
        else:
            box.scroll_page_up(animate=False)

    def action_help(self) -> None:
        self.push_screen(HelpScreen(panels.keys_text(self.ctl, False)))

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
