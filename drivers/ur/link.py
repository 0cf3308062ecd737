"""The driver's link to one UR controller and its supervision: ur_rtde's receive and control interfaces (RTDE,
port 30004; the control script goes up on 30003) next to the dashboard (29999) they share a host with.

ur_rtde never gives up on a link that vanished (a command waiting for its acknowledgement retries its reconnect
for minutes), so every command that waits for the controller runs ``bounded``: at most the RTDE stall timeout,
then the control interface is abandoned, a stop goes out over the dashboard and ``ConnectionLost`` is raised. Once
lost, the link stays lost until a reconnect (``URRobot.reconnect``) opens every channel again.

Units: seconds (``stale_timeout``, ``teardown_s``)."""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable

from station.drivers.ur.dashboard import DashboardClient

from station.robot.errors import BusError, ConnectionLost
from station.robot.registry import bus_library
from station.robot.silence import Silence

with bus_library("ur-rtde"):
    import rtde_control
    import rtde_receive

log = logging.getLogger("station.drivers.ur")

# The receive recipe: only what the driver reads (fewer bytes per 2 ms package than ur_rtde's default).
RECV_VARIABLES = ["timestamp", "actual_q", "actual_qd", "actual_TCP_pose", "actual_digital_input_bits",
                  "robot_mode", "safety_mode", "runtime_state", "robot_status_bits", "safety_status_bits"]


class RTDELink:
    """``receive`` (always, once connected) and ``control`` (from the first motion; None before and once
    abandoned) of one controller, with ``dashboard``. ``check()`` raises ConnectionLost once any of them is
    gone; ``bounded()`` runs a command that waits for the controller within ``stale_timeout``;
    ``on_abandon`` is called when a hanging command made the link give up its control interface."""

    def __init__(self, host: str, dashboard: DashboardClient, stale_timeout: float,
                 on_abandon: Callable[[], None] = lambda: None) -> None:
        self.host = host
        self.dashboard = dashboard
        self.stale_timeout = stale_timeout
        self.receive = None
        self.control = None
        self.lost = False
        # a control interface dropped while it hung in a call: kept referenced (destroying it would block on the
        # link) until the teardown releases it
        self.abandoned = None
        self._on_abandon = on_abandon

    # ---- opening and closing -----------------------------------------------------------------
    def open_receive(self) -> None:
        """The receive stream (nothing here needs the arm powered); a failure closes the dashboard too."""
        try:
            self.receive = rtde_receive.RTDEReceiveInterface(self.host, -1.0, RECV_VARIABLES)
        except Exception as e:
            self.dashboard.close()
            raise ConnectionLost(f"ur://{self.host}: RTDE (port 30004) connection failed: {e}") from None

    def open_control(self) -> None:
        """ur_rtde's RTDEControlInterface, without its own wait for the control script (``FLAG_NO_WAIT``, no
        upload by the constructor): the driver uploads the script and waits for it itself
        (``URRobot._start_script``), counting only time it observed. Its constructor's wait counts 10 ms sleeps
        up to 5 s."""
        flags = rtde_control.RTDEControlInterface.Flags.FLAG_NO_WAIT
        deadline = time.monotonic() + 2.0
        while True:
            try:
                self.control = rtde_control.RTDEControlInterface(self.host, -1.0, flags)
                return
            except Exception as e:  # noqa: BLE001 - ur_rtde raises RuntimeError
                # a previous client's connection may still be closing (its registers are freed when its socket
                # closes): give it a moment before calling the robot taken
                if "already in use" in str(e) and time.monotonic() < deadline:
                    time.sleep(0.2)
                    continue
                if "already in use" in str(e):
                    raise BusError(f"ur://{self.host}: another RTDE client already controls this robot (input "
                                   "registers in use); close it, or disable EtherNet/IP, PROFINET and MODBUS units "
                                   "on the controller") from None
                raise ConnectionLost(f"ur://{self.host}: RTDE control (script upload on 30003) failed: {e}") \
                    from None

    def drop(self) -> None:
        """Close both RTDE interfaces and the dashboard. ur_rtde's disconnect() waits 0.5 s after closing (with
        the GIL released): both interfaces at once."""
        def disconnect(obj) -> None:
            with contextlib.suppress(Exception):  # already broken: nothing to release
                obj.disconnect()

        workers = [threading.Thread(target=disconnect, args=(obj,), name="ur-disconnect", daemon=True)
                   for obj in (self.control, self.receive) if obj is not None]
        for t in workers:
            t.start()
        for t in workers:
            t.join()
        self.control = self.receive = None
        self.dashboard.close()

    def release_abandoned(self) -> None:
        """The control interface abandoned in a hanging call still holds its RTDE connection (and the input
        registers the next client needs): disconnect it where a hang does no harm, waited for a moment."""
        zombie, self.abandoned = self.abandoned, None
        if zombie is None:
            return

        def release() -> None:
            with contextlib.suppress(Exception):
                zombie.disconnect()

        t = threading.Thread(target=release, name="ur-abandoned-disconnect", daemon=True)
        t.start()
        t.join(1.0)

    def stop_program_after_loss(self, teardown_s: float) -> bool:
        """``stop`` over the dashboard (a fresh connection each try) until it answers or ``teardown_s`` passed;
        the control script ends with it, and a later connect uploads a fresh one. False (and a warning) if not."""
        deadline = time.monotonic() + teardown_s
        why: Exception | None = None
        while True:
            dash = DashboardClient(self.host, timeout=0.5)
            try:
                reply = dash.stop_program()
                log.info("ur://%s: program stopped over the dashboard after the link loss (%s)", self.host, reply)
                return True
            except (ConnectionLost, BusError) as e:
                why = e
            finally:
                dash.close()
            if time.monotonic() > deadline:
                break
            time.sleep(0.1)
        log.warning("ur://%s: could not stop the robot program after the link loss: the controller stayed "
                    "unreachable for %g s (%s); it may still run: press Stop on the teach pendant before "
                    "approaching the arm", self.host, teardown_s, why)
        return False

    # ---- supervision -------------------------------------------------------------------------
    def check(self) -> None:
        """ConnectionLost (one line) unless every open channel is connected. The control interface is opened
        with the first motion (None before); once abandoned or lost, the link is lost until a reconnect."""
        if self.receive is None or self.lost:
            self.lost = True
            raise ConnectionLost(f"ur://{self.host}: not connected to the controller; check the network, then "
                                 "resume the session")
        if not self.receive.isConnected() or (self.control is not None and not self.control.isConnected()):
            self.lost = True
            raise ConnectionLost(f"ur://{self.host}: connection to the controller lost (RTDE port 30004 closed); "
                                 "resume the session when the network is back")

    def check_moving(self) -> None:
        """During motion: on a lost RTDE link still try to stop the program over the dashboard (it may be a
        different failure than the network), then raise."""
        try:
            self.check()
        except ConnectionLost:
            with contextlib.suppress(ConnectionLost, BusError):
                self.dashboard.stop_program()
            raise

    def bounded(self, what: str, fn, *args):
        """``fn(*args)`` (a ur_rtde command that waits for the controller's acknowledgement) in a worker thread,
        waited for at most the RTDE stall timeout: ur_rtde releases the GIL but never gives up on a link that
        vanished (it retries its reconnect for minutes). On expiry the worker is abandoned with its control
        interface, a stop is sent over the dashboard in the background, and ConnectionLost is raised. The wait
        wakes every 20 ms, so Ctrl-C is acted on at once."""
        box: dict = {}
        done = threading.Event()

        def run() -> None:
            try:
                box["value"] = fn(*args)
            except BaseException as e:  # noqa: BLE001 - handed to the caller's thread
                box["error"] = e
            finally:
                done.set()

        threading.Thread(target=run, name=f"ur-{what}", daemon=True).start()
        silence = Silence()  # this process's own scheduling gaps are not the controller's silence
        try:
            while not done.wait(0.02):
                if silence.tick() > self.stale_timeout:
                    self.abandon_control()
                    raise ConnectionLost(f"ur://{self.host}: the controller did not acknowledge {what} within "
                                         f"{self.stale_timeout * 1e3:.0f} ms (RTDE stall timeout; "
                                         f"{silence.note()}): link lost, nothing more was sent and a stop went "
                                         "out over the dashboard; reconnect the robot when the network is back")
        except KeyboardInterrupt:  # wherever in the wait it lands: the command may still reach the controller
            # later, so never let it run; and the interface, still inside the call, must not be disconnected
            # under it at close (an interrupt outside the wait itself left it in place: ur_rtde crashed in
            # the teardown's disconnect, seen once in CI)
            if not done.is_set():
                self.abandon_control()
            raise
        if "error" in box:
            raise box["error"]
        return box["value"]

    def abandon_control(self) -> None:
        """The control interface hangs in a call: drop it (its worker thread is left to ur_rtde) so every later
        call fails fast with ConnectionLost, and stop the program over the dashboard without waiting for it."""
        if self.control is not None:
            self.control, self.abandoned = None, self.control
        self._on_abandon()
        self.lost = True

        def stop() -> None:
            with contextlib.suppress(Exception):
                DashboardClient(self.host, timeout=1.0).stop_program()

        threading.Thread(target=stop, name="ur-dashboard-stop", daemon=True).start()
