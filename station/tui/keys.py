"""Key releases for hold-to-run, where the terminal reports them: the kitty keyboard protocol's "report event
types" (progressive enhancement flag 2; kitty, foot, WezTerm, ghostty) sends a press ``CSI 113 u``, repeats
``CSI 113;1:2 u`` and a release ``CSI 113;1:3 u``
(https://sw.kovidgoyal.net/kitty/keyboard-protocol/#event-types).

Textual 8 pushes flags 1|8|16 (disambiguate, all keys as escape codes, associated text) but not flag 2, and its
parser reads the modifier field as one integer, so ``1:3`` would break its input thread. ``JogDriver`` ORs
flag 2 into the flags textual pushed (``CSI = 2 ; 2 u``; textual's pop at exit restores the terminal), and
``ReleaseParser`` takes the event type off before textual's own parsing: a repeat is a press to the app (the
hold-to-run keep-alive), a release becomes a ``Key`` named ``released_<key>`` that no binding matches and the
app reads in ``on_key``. A terminal without the protocol ignores the request and sends no event types: the
UI then infers the release from the autorepeat (``station.tui.controller.HOLD_*``)."""

from __future__ import annotations

import functools
import re
import threading
import time
from collections import deque
from collections.abc import Iterable

from textual import constants, events
from textual._xterm_parser import XTermParser
from textual.drivers import linux_driver

RELEASED = "released_"  # key-name prefix of a release event
REPORT_EVENT_TYPES = "\x1b[=2;2u"  # kitty: set (mode 2 = OR) flag 2 on the current stack entry
# CSI code[:alternates] ; modifiers : event-type [; text] final
_EVENT = re.compile(r"\x1b\[([\d:]*);(\d*):([123])((?:;[\d:]*)?)([u~A-Z])")


def split_event_type(sequence: str) -> tuple[str, int]:
    """``(sequence without its event type, type)``: 1 press, 2 repeat, 3 release (1 when none is given)."""
    m = _EVENT.fullmatch(sequence)
    if m is None:
        return sequence, 1
    code, mods, kind, text, final = m.groups()
    return f"\x1b[{code};{mods or '1'}{text}{final}", int(kind)


class KeyArrivals:
    """When the terminal input thread parsed each press or repeat of a key (``time.monotonic``), before the
    event waits in the UI's message queue. Hold-to-run infers a release from a gap in the autorepeat: measured
    here, a UI busy with a robot call cannot mistake its own lateness for a released key. Thread-safe: the
    input thread writes, the UI thread reads."""

    def __init__(self, keep: int = 64) -> None:
        self._keep = keep
        self._lock = threading.Lock()
        self._times: dict[str, deque[float]] = {}
        self._count: dict[str, int] = {}

    def note(self, key: str, t: float | None = None) -> None:
        with self._lock:
            self._times.setdefault(key, deque(maxlen=self._keep)).append(time.monotonic() if t is None else t)
            self._count[key] = self._count.get(key, 0) + 1

    def since(self, key: str, count: int) -> tuple[int, list[float]]:
        """``(arrivals of key so far, times of those numbered after count)``; (0, []) for a key never seen."""
        with self._lock:
            n = self._count.get(key, 0)
            times = self._times.get(key, ())
            new = max(0, min(n - count, len(times)))
            return n, list(times)[len(times) - new:] if new else []


class ReleaseParser(XTermParser):
    """Textual's parser, plus the kitty event types (above); notes every press/repeat in ``arrivals``."""

    def __init__(self, *args, arrivals: KeyArrivals | None = None, on_release=None, on_press=None,
                 **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.arrivals = arrivals
        self.on_release = on_release  # called with the key name on the input thread, before the event is queued
        self.on_press = on_press  # the same for every press and repeat (STOP acts here, ahead of the queue)

    def _sequence_to_key_events(self, sequence: str, alt: bool = False) -> Iterable[events.Key]:
        plain, kind = split_event_type(sequence)
        if kind != 3:
            for key in super()._sequence_to_key_events(plain, alt):
                if self.arrivals is not None:
                    self.arrivals.note(key.key)
                if self.on_press is not None:
                    self.on_press(key.key)
                yield key
            return
        for key in super()._sequence_to_key_events(plain, alt):
            if self.on_release is not None:
                self.on_release(key.key)
            yield events.Key(RELEASED + key.key, None)


class JogDriver(linux_driver.LinuxDriver):
    """Textual's Linux driver asking the terminal for key releases and parsing them."""

    def start_application_mode(self) -> None:
        super().start_application_mode()
        if not constants.DISABLE_KITTY_KEY:
            self.write(REPORT_EVENT_TYPES)
            self.flush()

    def run_input_thread(self) -> None:
        # LinuxDriver.run_input_thread builds its parser by this module-level name (textual 8 offers no
        # other hook); ReleaseParser parses everything else exactly as XTermParser does. The app's
        # ``key_arrivals`` (a KeyArrivals) gets the time of every press/repeat, ``key_released(key)`` every
        # release and ``key_pressed(key)`` every press at once (a release or a STOP must not wait behind the
        # UI's queue: the arm stops on it)
        linux_driver.XTermParser = functools.partial(ReleaseParser,
                                                     arrivals=getattr(self._app, "key_arrivals", None),
                                                     on_release=getattr(self._app, "key_released", None),
                                                     on_press=getattr(self._app, "key_pressed", None))
        super().run_input_thread()
