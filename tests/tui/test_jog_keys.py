"""Key releases from a terminal with the kitty keyboard protocol (station.tui.keys): textual's own parser with
the event types taken off, fed the byte sequences the protocol specifies
(https://sw.kovidgoyal.net/kitty/keyboard-protocol/#event-types)."""

from __future__ import annotations

import pytest
from textual import events

from station.tui.app import JOG_KEYS
from station.tui.keys import RELEASED, REPORT_EVENT_TYPES, ReleaseParser, split_event_type


def keys(data: str) -> list[str]:
    return [e.key for e in ReleaseParser().feed(data) if isinstance(e, events.Key)]


@pytest.mark.parametrize("press, repeat, release", [
    ("\x1b[113u", "\x1b[113;1:2u", "\x1b[113;1:3u"),  # flags 1|2|8: all keys as escape codes
    ("\x1b[113;;113u", "\x1b[113;1:2;113u", "\x1b[113;1:3u"),  # + flag 16: associated text (textual's set)
])
def test_press_repeat_release(press, repeat, release):
    assert keys(press + repeat + repeat + release) == ["q", "q", "q", RELEASED + "q"]


def test_every_jog_key_and_the_arrows():
    for plus, minus in JOG_KEYS:
        for k in (plus, minus):
            assert keys(f"\x1b[{ord(k)};1:3u") == [RELEASED + k]
    assert keys("\x1b[1;1:2A\x1b[1;1:3A") == ["up", RELEASED + "up"]


def test_plain_input_is_parsed_as_textual_does():
    assert keys("qa\r\x1b[A") == ["q", "a", "enter", "up"]
    assert split_event_type("\x1b[113;5u") == ("\x1b[113;5u", 1)  # ctrl+q, no event type
    assert split_event_type("\x1b[113;5:3u") == ("\x1b[113;5u", 3)
    assert REPORT_EVENT_TYPES == "\x1b[=2;2u"  # set flag 2 (report event types), OR mode


# Runs alone (exclusive), as a technician's station PC runs the jog UI: 3 of 3 at idle after the causes found were
# fixed (docs/jog.md). With the 2-core host overloaded (load 9-14) the station process is starved for 0.1-2 s and
# some holds stop late or do not start: docs/jog.md says so; it is a limit of the host, measured, not hidden here.
@pytest.mark.exclusive  # stop timing on the wire: run alone (make test)
@pytest.mark.timeout(180)
def test_kitty_release_stops_a_ur_hold_in_a_pty(tmp_path, emulators):
    """The real `station jog` in a pseudo-terminal typed at as kitty does with flag 2: it asks for event
    types, and the release of the held key stops the arm. Ground truth: the emulated controller's joint
    velocities (an independent RTDE client, controller clock)."""
    import os
    import subprocess
    import sys
    import threading
    import time

    import numpy as np
    import rtde_receive
    import yaml
    from station.mocks.world import default_doc

    doc = default_doc("ur5e", seed=11)
    doc["motion"].update(time_mode="sim", start=[0.1, -1.45, 1.6, -1.72, -1.5708, 0.2])
    doc["buses"] = {"ur": {"serial": "20235500011"}}
    (tmp_path / "world.yaml").write_text(yaml.safe_dump(doc))
    emu = emulators("ur", tmp_path / "world.yaml")
    master, slave = os.openpty()
    env = {**os.environ, "STATION_HOME": str(tmp_path / "home"), "TERM": "xterm-kitty", "COLUMNS": "160",
           "LINES": "50"}
    code = "import sys; from station.cli import main; sys.argv = ['station', *sys.argv[1:]]; main()"
    proc = subprocess.Popen([sys.executable, "-c", code, "jog", "--robot", emu.url, "--serial", "20235500011",
                             "--identify", "offsets"], stdin=slave, stdout=slave, stderr=slave, env=env,
                            start_new_session=True)
    os.close(slave)
    out = bytearray()

    def drain():
        while True:
            try:
                chunk = os.read(master, 65536)
            except OSError:
                return
            if not chunk:
                return
            out.extend(chunk)

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()

    def wait_for(text: bytes, timeout=60.0):
        end = time.monotonic() + timeout
        while text not in out:
            assert time.monotonic() < end and proc.poll() is None, bytes(out[-3000:])
            time.sleep(0.05)

    recv = rtde_receive.RTDEReceiveInterface(emu.host)

    def still_after(t_ctrl: float) -> float:
        end = time.monotonic() + 5
        while np.abs(recv.getActualQd()).max() > 1e-6:
            assert time.monotonic() < end, "still moving after the release"
            time.sleep(0.002)
        return recv.getTimestamp() - t_ctrl

    try:
        wait_for(b"live solve")
        assert REPORT_EVENT_TYPES.encode() in out  # the app asked the terminal for event types
        for k in (b"c", b"0"):
            os.write(master, k)
            time.sleep(0.5)
        q = "\x1b[113u", "\x1b[113;1:2u", "\x1b[113;1:3u"
        results = []
        for hold in (1.0, 1.0, 0.3):  # two holds with repeats, then a tap (released before any repeat)
            os.write(master, q[0].encode())
            t0 = time.monotonic()
            time.sleep(min(hold, 0.45))
            while time.monotonic() - t0 < hold:
                os.write(master, q[1].encode())
                time.sleep(0.033)
            moving = np.abs(recv.getActualQd()).max()
            os.write(master, q[2].encode())
            t_rel = recv.getTimestamp()
            results.append((hold, moving, still_after(t_rel)))
            time.sleep(0.4)
        os.write(master, b"\x11")
        proc.wait(timeout=60)
    finally:
        recv.disconnect()
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        os.close(master)
    for hold, moving, stop in results:
        print(f"kitty release on the UR: held {hold:.2f} s at {moving:.3f} rad/s, standstill {stop * 1e3:.0f} ms "
              "(controller time) after the release was written")
    # moving when released, the tap too (a loaded host may starve the station for a repeat gap: one miss)
    assert sum(moving > 1e-3 for _, moving, _ in results) >= 2, results
    assert results[-1][1] > 1e-3, results  # the tap
    for _, _moving, stop in results:
        # release -> app -> speedStop -> brake; the tap (0.3 s) without the release would run on until the
        # first-repeat window (0.6 s) ran out, ~0.5 s after the release
        assert stop < 0.1, stop  # within one watchdog period of the release
