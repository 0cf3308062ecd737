"""Records durability: the database is opened and proven writable before the robot moves; a store that
fails at the end leaves the run NOT STORED (exit 2, never PASS) with the journal complete, and
``station records sync`` stores it later from the journal (idempotent)."""

import contextlib
import os
import shutil
import sqlite3

import pytest
from clirunner import station_proc
from station.mocks.launch import launch

from station.api import run as start
from station.cli.run_cmd import BUS_OPTIONS, write_demo_files
from station.engine import read_journal
from station.records import RecordsError, open_records


@pytest.mark.parametrize("db, says", [
    ("nosuchdb://x/y", "bad database URL"),
    ("postgresql+psycopg://station@127.0.0.1:9/none", "cannot open records database"),  # nothing listens on 9
    ("READONLY", "does not take writes"),
])
def test_bad_database_is_one_line_before_the_robot_is_opened(tmp_path, db, says):
    if db == "READONLY":  # a real read-only SQLite connection to an existing database
        path = tmp_path / "ro.db"
        with open_records(f"sqlite:///{path}"):
            pass
        db = f"sqlite:///file:{path}?mode=ro&uri=true"
    env = {**os.environ, "STATION_HOME": str(tmp_path / "home")}
    r = station_proc("run", "zero_offsets", "--robot", "dynamixel:///dev/does-not-exist?model=omx", "--serial", "X",
                     "--db", db, env=env)
    assert r.code == 2, r.err
    lines = r.err_lines
    assert len(lines) == 1 and lines[0].startswith("station: error: ") and says in lines[0], r.err
    assert "does-not-exist" not in r.err  # the robot was never opened
    assert not (tmp_path / "home" / "sessions").exists() or not list((tmp_path / "home" / "sessions").iterdir())


def test_read_only_database_refused_by_the_api_before_motion(tmp_path, monkeypatch):
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    path = tmp_path / "ro.db"
    with open_records(f"sqlite:///{path}"):
        pass
    with pytest.raises(RecordsError, match="does not take writes"):
        start("zero_offsets", "dynamixel:///dev/does-not-exist?model=omx", "X",
              db=f"sqlite:///file:{path}?mode=ro&uri=true")


def test_database_lost_at_the_end_is_not_stored_then_synced(tmp_path, monkeypatch):
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    # the bus is not what is tested here: the Dynamixel arm (position-only plan, 4 joints) runs the same
    # zero_offsets session (24 touches, solve, report, store) in half the time of the 6-axis CiA 402 one
    world_path, cell_path, serial = write_demo_files("dynamixel", tmp_path, seed=21, time_mode="instant")
    dbfile = tmp_path / "records.db"
    db = f"sqlite:///{dbfile}"

    def progress(done, total, text):
        if done == total and dbfile.is_file():  # the database goes away after the last sample: a directory
            dbfile.unlink()                    # where the file was cannot be opened by SQLite
            dbfile.mkdir()

    with launch("dynamixel", world_path, serial=serial) as emu:
        out = start("zero_offsets", emu.url, serial, cell=cell_path, db=db, options=dict(BUS_OPTIONS["dynamixel"]),
                    progress=progress)
    assert out.verdict == "NOT STORED" and out.exit_code == 2 and not out.stored and out.store_error
    assert out.report is not None and out.report.exists()  # the report is written all the same
    header, events = read_journal(out.folder / "journal.jsonl")
    assert events[-1].type == "end" and events[-1].status == "completed"  # the journal is complete
    n = len([e for e in events if e.type == "sample"])
    env = {**os.environ, "STATION_HOME": str(tmp_path / "home")}
    r = station_proc("records", "sync", out.session, env=env)  # the database still down: one line, exit 2
    assert r.code == 2 and r.err.count("station: error:") == 1, r.err
    shutil.rmtree(dbfile)  # the database is back
    r = station_proc("records", "sync", env=env)  # no id: every ended session not stored yet
    assert r.code == 0 and f"{out.session}: stored" in r.out, r.err
    r = station_proc("records", "sync", env=env)
    assert r.code == 0 and f"{out.session}: already stored" in r.out, r.err
    r = station_proc("records", "sync", out.session, env=env)  # named: the same record is there, nothing is written
    assert r.code == 0 and f"{out.session}: already stored" in r.out, r.out + r.err
    with open_records(db) as rec:
        stored = rec.session(out.session)
        (summary,) = rec.sessions(serial)
    assert len(stored["samples"]) == n and summary["passed"] == out.passed is not None
    assert summary["status"] == "completed" and summary["store_count"] == 1
    con = sqlite3.connect(dbfile)
    assert con.execute("select count(*) from samples").fetchone()[0] == n  # no duplicates after 3 syncs
    con.close()


def test_not_stored_on_the_command_line(tmp_path):
    """``station run`` whose database fails at the end: NOT STORED, exit 2, a sync hint, never PASS."""
    world_path, cell_path, serial = write_demo_files("dynamixel", tmp_path, seed=22, time_mode="instant")
    dbfile = tmp_path / "records.db"
    env = {**os.environ, "STATION_HOME": str(tmp_path / "home")}
    # the records database goes away while the station solves (after the last sample): a wrapper around the
    # station's own entry point swaps the file for a directory, which SQLite cannot open
    prelude = (
        "from pathlib import Path\n"
        "import station.engine.session as S\n"
        "orig = S.Session.solve\n"
        f"db = Path({str(dbfile)!r})\n"
        "def solve(self, *a, **k):\n"
        "    if db.is_file():\n"
        "        db.unlink(); db.mkdir()\n"
        "    return orig(self, *a, **k)\n"
        "S.Session.solve = solve\n")
    with launch("dynamixel", world_path, serial=serial, process=True) as emu:
        r = station_proc("run", "zero_offsets", "--robot", emu.url, "--serial", serial, "--cell", cell_path,
                         "--db", f"sqlite:///{dbfile}", "-q", "--reference", "cell", "--cone", "70",
                         timeout=300, env=env, prelude=prelude)
    assert r.code == 2, r.err
    assert r.out.strip().splitlines()[-1] == "NOT STORED" and "PASS" not in r.out.splitlines()[-1]
    errors = r.errors
    assert len(errors) == 1 and "record not stored" in errors[0], r.err
    assert "station records sync" in r.err and "station resume" not in r.err


class _Outage:
    """A TCP relay in front of the PostgreSQL server: the station's records URL points here, so the test can cut
    the database off mid-session (every connection reset, the port refused) and bring it back on the same port."""

    def __init__(self, host: str, port: int):
        import socket
        import threading

        self.target, self.threading, self.socket = (host, port), threading, socket
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.conns: list = []
        self.up = True
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self):
        while True:
            try:
                c, _ = self.listener.accept()
            except OSError:
                return
            if not self.up:
                c.close()
                continue
            s = self.socket.create_connection(self.target)
            self.conns += [c, s]
            for a, b in ((c, s), (s, c)):
                self.threading.Thread(target=self._pipe, args=(a, b), daemon=True).start()

    @staticmethod
    def _pipe(a, b):
        try:
            while data := a.recv(65536):
                b.sendall(data)
        except OSError:
            pass
        finally:
            for x in (a, b):
                with contextlib.suppress(OSError):
                    x.close()

    def down(self):
        self.up = False
        for c in self.conns:
            with contextlib.suppress(OSError):
                c.shutdown(self.socket.SHUT_RDWR)
        self.conns = []

    def close(self):
        self.down()
        self.listener.close()


@pytest.mark.postgres
def test_postgres_outage_at_the_end_is_not_stored_then_synced(tmp_path, monkeypatch, pg_url):
    """The factory database (a real PostgreSQL) becomes unreachable after the last sample: NOT STORED, exit 2,
    never PASS, journal complete; ``station records sync`` stores it once the server is reachable again,
    a second sync adds no duplicate rows."""
    from sqlalchemy.engine import make_url

    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    real = make_url(pg_url)
    relay = _Outage(real.host or "127.0.0.1", real.port or 5432)
    db = real.set(host="127.0.0.1", port=relay.port).render_as_string(hide_password=False)
    world_path, cell_path, serial = write_demo_files("dynamixel", tmp_path, seed=23, time_mode="instant")
    serial = f"{serial}-{tmp_path.name[-12:]}"  # unique in a shared server
    try:
        def progress(done, total, text):
            if done == total:
                relay.down()

        with launch("dynamixel", world_path, serial=serial) as emu:
            out = start("zero_offsets", emu.url, serial, cell=cell_path, db=db, report=False,
                        options=dict(BUS_OPTIONS["dynamixel"]), progress=progress)
        assert out.verdict == "NOT STORED" and out.exit_code == 2 and out.passed is not None, \
            (out.verdict, out.error, out.store_error)
        assert out.store_error and "\n" not in out.store_error
        events = read_journal(out.folder / "journal.jsonl")[1]
        assert events[-1].type == "end" and events[-1].status == "completed"
        n = len([e for e in events if e.type == "sample"])
        env = {**os.environ, "STATION_HOME": str(tmp_path / "home")}
        r = station_proc("records", "sync", out.session, env=env)  # still unreachable: one line, exit 2
        assert r.code == 2 and r.err.count("station: error:") == 1, r.err
        relay.up = True  # the server is reachable again
        for want in ("stored", "already stored"):
            r = station_proc("records", "sync", env=env)
            assert r.code == 0 and f"{out.session}: {want}" in r.out, (r.out, r.err)
        with open_records(pg_url) as rec:
            stored = rec.session(out.session)
            (summary,) = rec.sessions(serial)
        assert len(stored["samples"]) == n and summary["passed"] == out.passed
    finally:
        relay.close()
