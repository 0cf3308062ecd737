"""station.robot.silence: a stall timeout counts the link's silence, not the watcher's own absences."""

from station.robot.silence import Silence


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_short_turns_count_in_full_and_a_gap_of_the_watcher_counts_own_gap_at_most():
    clock = Clock()
    s = Silence(own_gap=0.05, clock=clock)
    for _ in range(30):  # a loop turning every 10 ms: 0.3 s of silence
        clock.t += 0.010
        s.tick()
    assert abs(s.seconds - 0.30) < 1e-9
    clock.t += 2.0  # the watcher was not scheduled for 2 s (a loaded PC, a paused VM)
    assert abs(s.tick() - 0.35) < 1e-9
    for _ in range(20):  # the link still silent while the watcher watches again: it adds up
        clock.t += 0.010
        s.tick()
    assert abs(s.seconds - 0.55) < 1e-9
    s.reset()  # new data
    clock.t += 0.010
    assert abs(s.tick() - 0.010) < 1e-9


def test_a_dead_link_is_still_called_dead_within_the_threshold_while_the_watcher_runs():
    clock = Clock()
    s = Silence(clock=clock)
    turns = 0
    while s.tick() <= 0.5:
        clock.t += 0.004
        turns += 1
    assert abs(turns * 0.004 - 0.5) < 0.01  # 0.5 s of watching, not more


def test_the_note_says_the_hosts_longest_gap_and_what_was_not_counted():
    clock = Clock()
    s = Silence(own_gap=0.05, clock=clock)
    clock.t += 0.010
    s.tick()
    clock.t += 1.2  # the watcher was not scheduled for 1.2 s
    s.tick()
    s.reset()  # new data: the silence starts again, the host's record stays
    clock.t += 0.010
    s.tick()
    assert abs(s.seconds - 0.010) < 1e-9 and abs(s.max_gap - 1.2) < 1e-9 and abs(s.uncounted - 1.15) < 1e-9
    assert s.note() == "host scheduling gap: longest 1200 ms, 1150 ms not counted as silence"
