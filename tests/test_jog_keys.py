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
