"""Durability of the session journal: an append that cannot complete (short write, ENOSPC, a real
RLIMIT_FSIZE refusal) leaves the journal valid and the session never PASS; free space and a writable sessions
folder are checked before anything moves; a torn last line is reported and kept, never silently dropped."""

import errno
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from clirunner import station_proc
from faultrig import demo_cell

from station.api import resume
from station.api import run as start
from station.cli.run_cmd import BUS_OPTIONS
from station.engine import events as ev
from station.engine.journal import Journal, JournalWriteError, read_journal, torn_tail


def _header(sid="S-1"):
    return ev.Header(session=sid, procedure="zero_offsets", serial="X", url="canopen+virtual://x")


def _sample(i):
    return ev.Sample(point="A", q=[0.1 * i, 0.2, 0.3], pose=i)


def _lines_ok(path):
    data = path.read_bytes()
    assert data.endswith(b"\n")
    return read_journal(path)


def test_short_write_is_cut_back_and_next_event_lands_on_its_own_line(tmp_path, monkeypatch):
    j = Journal.create(tmp_path / "journal.jsonl", _header())
    j.append(_sample(0))
    size = (tmp_path / "journal.jsonl").stat().st_size
    real_write = os.write
    calls = {"n": 0}

    def short_then_full(fd, data):  # the disk fills mid-line: half a line, then ENOSPC
        calls["n"] += 1
        if calls["n"] == 1:
            return real_write(fd, data[: len(data) // 2])
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "write", short_then_full)
    with pytest.raises(JournalWriteError, match="No space left on device"):
        j.append(_sample(1))
    assert (tmp_path / "journal.jsonl").stat().st_size == size  # the half line was cut off again
    assert j.lost == ["sample"]
    monkeypatch.setattr(os, "write", real_write)  # space returns
    j.append(_sample(2))
    j.close()
    header, events = _lines_ok(tmp_path / "journal.jsonl")
    assert [e.pose for e in events] == [0, 2]  # nothing glued onto a half line
    assert torn_tail(tmp_path / "journal.jsonl") is None


def test_a_write_that_returns_zero_is_an_error_not_a_loop(tmp_path, monkeypatch):
    j = Journal.create(tmp_path / "journal.jsonl", _header())
    monkeypatch.setattr(os, "write", lambda fd, data: 0)
    with pytest.raises(JournalWriteError, match="short write"):
        j.append(_sample(0))
    monkeypatch.undo()
    j.close()
    assert read_journal(tmp_path / "journal.jsonl")[1] == []


def test_real_file_size_limit_refusal_leaves_the_journal_valid(tmp_path):
    """The kernel refuses the write (RLIMIT_FSIZE: EFBIG / a short write), no monkeypatching."""
    path = tmp_path / "journal.jsonl"
    code = textwrap.dedent(f"""
        import resource, signal, sys
        from station.engine import events as ev
        from station.engine.journal import Journal, JournalWriteError
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        j = Journal.create({str(path)!r}, ev.Header(session="S", procedure="p", serial="X", url="x://y"))
        j.append(ev.Sample(point="A", q=[0.1, 0.2], pose=0))
        size = j.path.stat().st_size
        resource.setrlimit(resource.RLIMIT_FSIZE, (size + 40, resource.RLIM_INFINITY))
        try:
            j.append(ev.Sample(point="A", q=[0.3] * 50, pose=1))
        except JournalWriteError as e:
            print("ERR", e)
            sys.exit(3)
        print("NO ERROR")
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 3, (r.stdout, r.stderr)
    assert "could not write the sample event" in r.stdout and "\n" not in r.stdout.strip()
    header, events = _lines_ok(path)
    assert [e.pose for e in events] == [0]


def test_torn_last_line_is_reported_and_kept(tmp_path):
    path = tmp_path / "journal.jsonl"
    j = Journal.create(path, _header())
    j.append(_sample(0))
    j.close()
    with open(path, "ab") as fh:
        fh.write(b'{"type":"sample","point":"A","q":[0.1')  # power lost mid-line
    assert "journal" in torn_tail(path) and ":3:" in torn_tail(path)
    again = Journal.open(path)
    assert again.torn and "kept in journal.jsonl.torn" in again.torn
    assert (tmp_path / "journal.jsonl.torn").read_bytes().startswith(b'{"type":"sample","point":"A","q":[0.1')
    again.append(_sample(1))
    again.close()
    assert [e.pose for e in _lines_ok(path)[1]] == [0, 1]


# ---- whole sessions on the CANopen emulator (real canopen library on a python-can virtual bus) ---------------
@pytest.fixture
def cell(tmp_path, monkeypatch):
    with demo_cell("canopen", tmp_path, seed=21) as c:
        monkeypatch.setenv("STATION_HOME", str(c.home))
        yield c.emu, c.cell_path, c.serial, c.db


def _samples(path):
    return [e for e in read_journal(path)[1] if e.type == "sample"]


def test_disk_full_mid_session_is_an_error_then_resume_completes(cell, monkeypatch):
    emu, cell_path, serial, db = cell
    real_write = os.write
    state = {"full": False, "journal_ino": None}

    def write(fd, data):
        if state["full"] and os.fstat(fd).st_ino == state["journal_ino"]:
            return real_write(fd, data[:7]) if len(data) > 7 else 0  # a short write, then nothing
        return real_write(fd, data)

    def progress(done, total, text):
        if done == 4 and state["journal_ino"] is None:
            j = next(Path(os.environ["STATION_HOME"]).glob("sessions/*/journal.jsonl"))
            state["journal_ino"], state["full"] = j.stat().st_ino, True

    monkeypatch.setattr(os, "write", write)
    out = start("zero_offsets", emu.url, serial, cell=cell_path, db=db, options=dict(BUS_OPTIONS["canopen"]),
                progress=progress)
    assert out.status == "error" and out.exit_code == 2 and out.passed is None and out.verdict == "ERROR"
    assert isinstance(out.error, JournalWriteError) and "\n" not in str(out.error)
    assert not emu.world.is_moving()
    path = out.folder / "journal.jsonl"
    kept = _samples(path)
    assert len(kept) == 4 and path.read_bytes().endswith(b"\n")  # valid: every line a whole event
    assert not any(e.type == "end" for e in read_journal(path)[1])  # the end could not be written: resumable
    state["full"] = False  # space returns
    done = resume(out.session, db=db)
    assert done.status == "completed" and done.verdict in ("PASS", "FAIL"), done.error
    samples = _samples(path)
    assert sorted(s.pose for s in samples) == list(range(24))  # nothing lost, nothing repeated
    assert samples[:4] == kept


def test_free_space_is_checked_before_the_robot_is_opened(tmp_path, monkeypatch):
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    monkeypatch.setenv("STATION_MIN_FREE_MB", str(10 ** 9))  # a petabyte: more than any disk has free
    r = station_proc("run", "zero_offsets", "--robot", "dynamixel:///dev/does-not-exist?model=omx", "--serial", "X",
                     "--db", f"sqlite:///{tmp_path / 'r.db'}", timeout=120)  # the environment set above
    assert r.code == 2
    lines = r.err_lines
    assert len(lines) == 1 and lines[0].startswith("station: error: only ") and "MiB free" in lines[0], r.err
    assert not list((tmp_path / "home" / "sessions").glob("*"))  # no session was started


def test_free_space_is_checked_before_each_motion(cell, monkeypatch):
    emu, cell_path, serial, db = cell

    def progress(done, total, text):
        if done == 3:
            monkeypatch.setenv("STATION_MIN_FREE_MB", str(10 ** 9))

    out = start("zero_offsets", emu.url, serial, cell=cell_path, db=db, options=dict(BUS_OPTIONS["canopen"]),
                progress=progress)
    assert out.exit_code == 2 and "MiB free" in str(out.error)
    events = read_journal(out.folder / "journal.jsonl")[1]
    fault = next(e for e in events if e.type == "fault")
    assert (fault.step, fault.pose) == ("approach", 3)  # named for the pose-loop action, not "plan"
    assert len([e for e in events if e.type == "sample"]) == 3


def test_read_only_sessions_folder_is_one_line_before_the_robot_is_opened(tmp_path, monkeypatch):
    """A real read-only file system when the test may mount one (root), else a directory without write
    permission (non-root)."""
    home = tmp_path / "home"
    sessions = home / "sessions"
    sessions.mkdir(parents=True)
    mounted = False
    if os.geteuid() == 0:
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(sessions)],
                           capture_output=True, text=True)
        mounted = r.returncode == 0
        if not mounted:
            pytest.skip(f"running as root and cannot mount a read-only tmpfs: {r.stderr.strip()}")
    else:
        sessions.chmod(0o555)
    try:
        env = {**os.environ, "STATION_HOME": str(home)}
        r = station_proc("run", "zero_offsets", "--robot", "dynamixel:///dev/does-not-exist?model=omx",
                         "--serial", "X", "--db", f"sqlite:///{tmp_path / 'r.db'}", timeout=120, env=env)
    finally:
        if mounted:
            subprocess.run(["umount", str(sessions)], check=True)
        else:
            sessions.chmod(0o755)
    assert r.code == 2
    lines = r.err_lines
    assert len(lines) == 1 and lines[0].startswith(f"station: error: cannot write session journals in {sessions}"), \
        r.err
    assert "does-not-exist" not in r.err  # the robot was never opened
