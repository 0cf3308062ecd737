"""Hold-to-run: the arm moves while a jog key is held and stops when it is released (docs/jog.md
"Hold-to-run"). One ``HoldToRun`` per ``JogController``: it keeps the terminal's measured key cadence and the
running hold, and moves the robot through the controller (its jog targets, speed rules and keep-out checks)."""

from __future__ import annotations

import statistics
import time
from collections import deque
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from station.robot.errors import LimitError, StationError
from station.robot.motion import joint_speed_for_tool_cap

if TYPE_CHECKING:
    from contextlib import AbstractContextManager

    from station.kinematics import Model

# hold-to-run (docs/jog.md "Hold-to-run"). A terminal with the kitty keyboard protocol reports the key release
# (station.tui.keys): the release stops at once. Elsewhere only the autorepeat shows a held key: the press, a
# repeat delay (250-600 ms), then a repeat every 30-40 ms. The release is then inferred from a gap of
# HOLD_GAP_REPEATS measured repeat intervals, never shorter than HOLD_GAP_MIN_S (terminal input jitter) and
# never longer than HOLD_RELEASE_S (the UR's RTDE watchdog period). Before the first repeat of a hold the
# window is the terminal's repeat delay as measured on earlier holds (HOLD_FIRST_S until one was measured), so
# the first press never stop-starts the arm (a "delay" under HOLD_DELAY_MIN_S is a hold resumed mid-repeat,
# never learned). Key times are when the terminal input thread parsed the key (``key_arrivals``,
# station.tui.keys.KeyArrivals), not when the busy UI got round to it. The UI checks for a release every
# HOLD_CHECK_S and re-commands the motion every HOLD_TICK_S; every position target ends where the arm would be
# shortly after the deadline, so a stalled UI stops it there too (HOLD_WATCHDOG_S: standstill after the last
# key event).
HOLD_RELEASE_S = 0.1
HOLD_GAP_REPEATS = 2.5
HOLD_GAP_MIN_S = 0.05
HOLD_TICK_S = 0.05
HOLD_CHECK_S = 0.01
HOLD_WATCHDOG_S = 0.3
HOLD_FIRST_S = 0.6
RELEASE_LOCK_S = 0.2  # s: a release waits at most this for a re-command in flight, then stops regardless
HOLD_DELAY_MIN_S = 0.15  # s: no terminal's repeat delay is shorter


class Jogger(Protocol):
    """What hold-to-run needs of the jog controller that owns it (``station.tui.controller.JogController``): its
    robot and model, the jog a key makes, its lock, STOP, and where it says what happened. Written here, so this
    part does not import the controller that imports it."""

    robot: Any
    model: Model
    io_lock: AbstractContextManager
    mode: str  # joint | cartesian
    frame: str  # base | tool
    axis: int
    velocity_jog: bool
    fault: str | None
    message: str
    last_jog: dict | None

    @property
    def speed_percent(self) -> int: ...

    @property
    def speed_mm_s(self) -> float: ...

    def axis_names(self) -> list[str]: ...

    def axis_unit(self, axis: int) -> str: ...

    def joint_rate(self, axis: int) -> float: ...

    def lead_rate(self, axis: int, q0: np.ndarray, target: np.ndarray, step: float) -> float: ...

    def target(self, q0: np.ndarray, axis: int, step: float) -> np.ndarray: ...

    def stop(self, quiet: bool = False) -> None: ...

    def _refuse_axis(self, axis: int) -> str | None: ...

    def _on_error(self, err: StationError, what: str) -> None: ...


class HoldToRun:
    """The hold-to-run part of a ``JogController`` (``ctl``): key events in, motion commands out."""

    def __init__(self, ctl: Jogger) -> None:
        self.ctl = ctl
        self.hold_state: dict | None = None
        self.repeat_intervals: deque[float] = deque(maxlen=16)  # the terminal's autorepeat, measured (s)
        self.repeat_delay: float | None = None  # the terminal's delay before the first repeat, measured (s)
        self.release_events = False  # the terminal reported a key release (kitty keyboard protocol)
        # (axis, direction, count) -> (arrivals so far, times of those after count) of that jog key as the
        # terminal's input thread saw them (set by the app; None: key times are the calls' ``now``)
        self.key_arrivals = None
        self._arrival_mark: dict[tuple[int, int], int] = {}  # arrivals already taken by an ended hold
        self._idle_kick = 0.0

    def hold(self, axis: int, direction: int, now: float | None = None) -> bool:
        """A jog key event in hold-to-run mode (the press or one of the terminal's repeats): keep moving
        ``axis`` while events keep coming; :meth:`hold_tick` stops the robot once they stop."""
        refusal = self.ctl._refuse_axis(axis)
        if refusal:
            self.ctl.message = refusal
            return False
        now = time.monotonic() if now is None else now
        d = 1 if direction > 0 else -1
        h = self.hold_state
        if h is not None and h["axis"] == axis and h["dir"] == d and h["mode"] == self.ctl.mode:
            if not self._arrivals_seen(h):
                self._repeat_seen(h, now)
            return True
        seen, times = self._arrivals(axis, d, self._arrival_mark.get((axis, d), 0))
        # the press as the terminal delivered it: the first arrival of this key after the last hold, unless
        # older than a repeat delay (step presses before hold-to-run was chosen, or a UI stalled that long)
        times = [t for t in times if t >= now - HOLD_FIRST_S]
        if seen and not times:
            # a repeat that arrived before the held key's release (or the inferred one) and waited in the UI's
            # queue: the key is no longer held, so it must not start the arm again
            return False
        if h is not None:
            self.stop_hold(quiet=True)
        self.ctl.axis = axis
        t0 = times[0] if times else now
        self.hold_state = h = {"axis": axis, "dir": d, "mode": self.ctl.mode, "frame": self.ctl.frame, "events": 1,
                               "deadline": t0 + self.first_window(), "started": t0, "last": t0, "sent": None,
                               "seen": seen - len(times) + 1 if times else seen}
        self._arrivals_seen(h)  # repeats that arrived while the press waited in the UI's queue
        return self._hold_command(now)

    def _end_hold(self) -> None:
        h, self.hold_state = self.hold_state, None
        if h is not None:  # the key's arrivals so far belong to the ended hold; the next press comes after them
            self._arrival_mark[(h["axis"], h["dir"])] = self._arrivals(h["axis"], h["dir"], 0)[0]

    def _arrivals(self, axis: int, d: int, count: int) -> tuple[int, list[float]]:
        if self.key_arrivals is None:
            return 0, []
        return self.key_arrivals(axis, d, count)

    def _arrivals_seen(self, h: dict) -> bool:
        """Take the held key's repeats the input thread saw since the last look (their own times). False when
        there are no arrival times (no terminal input thread: the caller's ``now`` counts)."""
        seen, times = self._arrivals(h["axis"], h["dir"], h["seen"])
        if not seen:
            return False
        h["seen"] = seen
        for t in times:
            self._repeat_seen(h, max(t, h["last"]))
        return True

    def _repeat_seen(self, h: dict, now: float) -> None:
        """A repeat of the held key: measure the terminal's cadence and move the release deadline."""
        dt = now - h["last"]
        if h["events"] == 1:
            h["delay"] = dt  # the repeat delay (or a second press: confirmed by the cadence that follows)
        else:
            self.repeat_intervals.append(dt)
            if h["events"] == 2 and dt < 0.6 * h["delay"] and h["delay"] >= HOLD_DELAY_MIN_S:
                self.repeat_delay = h["delay"]
        h["events"] += 1
        h["last"] = now
        h["deadline"] = now + self.release_gap()

    def release_gap(self) -> float:
        """Key-event gap taken as a release: HOLD_GAP_REPEATS measured repeat intervals (mean of the last
        16), within [HOLD_GAP_MIN_S, HOLD_RELEASE_S]; HOLD_RELEASE_S until the cadence was measured, and in a
        terminal that reports releases (a lost release still stops within the watchdog period)."""
        if not self.repeat_intervals or self.release_events:
            return HOLD_RELEASE_S  # (the terminal reports releases: the gap is only the backup)
        # the mean, not the median: a busy UI receives repeats in bunches (intervals near 0 then one long),
        # whose median would shrink the gap below the real cadence
        est = statistics.fmean(self.repeat_intervals)
        return float(min(HOLD_RELEASE_S, max(HOLD_GAP_MIN_S, HOLD_GAP_REPEATS * est)))

    def first_window(self) -> float:
        """How long a press keeps the arm moving before its first repeat: the measured repeat delay plus a
        quarter (input jitter), at most HOLD_FIRST_S; HOLD_FIRST_S until a delay was measured."""
        if self.repeat_delay is None:
            return HOLD_FIRST_S
        return float(min(HOLD_FIRST_S, self.repeat_delay + max(HOLD_GAP_MIN_S, 0.25 * self.repeat_delay)))

    def release(self, axis: int, direction: int) -> None:
        """The terminal reported the release of a jog key (kitty keyboard protocol): stop now if it is the
        held one. Safe from the terminal's input thread (the app calls it there, ahead of the UI's queue): a
        re-command in flight is waited for (``io_lock``, at most RELEASE_LOCK_S) and none starts after the hold
        ended (``_hold_command`` re-checks under the lock). If the lock does not come free, a velocity jog is
        stopped anyway (``stop()`` bypasses the lock, as the STOP key does); a position-controlled robot (bus
        not thread-safe) is left to the same release on the UI thread, its targets end near the deadline."""
        self.release_events = True
        d = 1 if direction > 0 else -1
        locked = self.ctl.io_lock.acquire(timeout=RELEASE_LOCK_S)
        try:
            # every press/repeat of this key so far belongs to before the release: one still queued for the UI
            # (this runs ahead of the queue) is stale and must not start the arm after the key came up
            self._arrival_mark[(axis, d)] = self._arrivals(axis, d, 0)[0]
            h = self.hold_state
            if h is None or h["axis"] != axis or h["dir"] != d or not (locked or self.ctl.velocity_jog):
                return
            self._end_hold()
            self.ctl.stop(quiet=True)
            self.ctl.message = "key released: stopped"
        finally:
            if locked:
                self.ctl.io_lock.release()

    def hold_check(self, now: float | None = None) -> bool:
        """Stop once the release deadline passed (cheap: the UI calls it every HOLD_CHECK_S). True if it stopped."""
        h = self.hold_state
        if h is None:
            return False
        now = time.monotonic() if now is None else now
        if now >= h["deadline"]:
            self._arrivals_seen(h)  # a repeat may wait in the UI's queue: the key is still held
            if now < h["deadline"]:
                return False
            self.stop_hold()
            return True
        return False

    def hold_tick(self, now: float | None = None) -> None:
        """Called by the UI every HOLD_CHECK_S: stop once the key events stopped, else re-command the held
        motion every HOLD_TICK_S."""
        now = time.monotonic() if now is None else now
        if self.hold_check(now):
            return
        h = self.hold_state
        if h is None or (h["sent"] is not None and now - h["sent"] < HOLD_TICK_S * 0.9):
            return
        self._hold_command(now)

    def hold_idle(self, now: float | None = None) -> None:
        """Called by the UI between holds: a velocity-jog robot's watchdog stays armed after a release (UR:
        the RTDE watchdog lives as long as the control script), so keep feeding it every HOLD_TICK_S; else the
        controller ends the program a watchdog period after each release and the next press waits for the
        script to be uploaded again. If the UI stalls anyway, the next press restarts it (slower, still safe)."""
        c = self.ctl
        keep = getattr(c.robot, "jog_keep_alive", None) if c.velocity_jog and not c.fault else None
        now = time.monotonic() if now is None else now
        if keep is None or now - self._idle_kick < HOLD_TICK_S or not self.ctl.io_lock.acquire(blocking=False):
            return
        try:
            self._idle_kick = now
            keep()
        except StationError as e:
            self.ctl._on_error(e, "jog watchdog")
        finally:
            self.ctl.io_lock.release()

    def stop_hold(self, quiet: bool = False) -> None:
        if self.hold_state is None:
            return
        self.ctl.stop(quiet=True)
        if not quiet:
            self.ctl.message = "key released: stopped"

    def _hold_command(self, now: float) -> bool:
        """Command a target no farther than the robot travels at the override until the deadline: if the UI
        stalls, the robot still stops there by itself."""
        c = self.ctl
        h = self.hold_state
        if h is None:
            return False
        h["sent"] = now
        # the target is where the arm would be two ticks after the deadline (a target much closer makes the
        # drives' profiles brake between commands): a stalled UI still stops the arm there
        horizon = max(h["deadline"] - now, 0.0) + 2 * HOLD_TICK_S
        axis, d = h["axis"], h["dir"]
        cap = c.speed_mm_s * 1e-3
        rotational = c.axis_unit(axis) == "deg"
        rate = c.joint_rate(axis)
        with c.io_lock:
            if self.hold_state is not h:  # released (from the input thread) while this waited for the lock
                return False
            try:
                q0 = np.asarray(c.robot.joint_positions().q, dtype=float)
                if c.velocity_jog:
                    sent = self._hold_velocity(axis, d, q0, cap, rate)
                else:
                    step = d * (rate if rotational or c.mode == "joint" else cap) * horizon
                    target = c.target(q0, axis, step)
                    speed = joint_speed_for_tool_cap(c.model, q0, target, c.lead_rate(axis, q0, target, step), cap=cap)
                    lead = float(np.max(np.abs(target - q0)))
                    if lead > speed * horizon > 0:  # slower than asked (tool cap): shorten to the reachable part
                        step *= speed * horizon / lead
                        target = c.target(q0, axis, step)
                    c.robot.move_joints(target, speed=speed, wait=False)
                    sent = {"step": step, "speed": speed, "target": target}
            except LimitError as e:
                c.stop(quiet=True)
                c.message = f"refused: {e}"
                return False
            except StationError as e:
                self._end_hold()
                c._on_error(e, f"jog {c.axis_names()[axis]}")
                return False
        c.last_jog = {"mode": c.mode, "frame": c.frame, "axis": axis, "q0": q0, "cap_m_s": cap, "hold": True, **sent}
        c.message = (f"hold-to-run {c.axis_names()[axis]} {'+' if d > 0 else '-'} at {c.speed_percent} % "
                     f"({c.speed_mm_s:g} mm/s)")
        return True

    def _hold_velocity(self, axis: int, d: int, q0: np.ndarray, cap: float, rate: float) -> dict:
        """Velocity hold (caller holds io_lock and handles errors): re-send the speed each tick; the driver's
        watchdog stops the arm if the ticks stop. Joint speed is limited so the tool stays within the override."""
        if self.ctl.mode == "joint":
            probe = self.ctl.target(q0, axis, d * 1e-3)  # direction of motion, for the tool-speed bound
            speed = joint_speed_for_tool_cap(self.ctl.model, q0, probe, rate, cap=cap)
        elif self.ctl.axis_unit(axis) == "deg":
            self.ctl.target(q0, axis, d * 1e-3)  # reachable and clear of the keep-out (LimitError otherwise)
            speed = rate  # rad/s about the TCP: the override's share of 30 deg/s
        else:
            speed = cap
        self.ctl.robot.jog_velocity(self.ctl.mode, axis, d * speed, self.ctl.frame)
        return {"velocity": d * speed}
