"""The one way tests run the ``station`` command: ``station_main`` in this process (the same ``main`` the installed
command runs; emulators on in-process buses stay reachable), ``station_proc`` as a child process (the installed
console script or ``python -m station.cli``: its own interpreter, exit path and environment). Both return a
``CliResult``: exit code, stdout, stderr.

    from clirunner import station_main, station_proc
    r = station_main("solve", "--model", "ur5e", "--samples", path)
    assert r.code == 2 and r.error_line().startswith("station: error: ")

A child that must be signalled, killed or read while it runs: ``station_spawn`` (the command) or ``python_spawn``
(a script that drives a robot through the API in an interpreter of its own, when the test needs a second
process and no command does what the script does). Both give a ``ChildProcess``; as a context manager it kills
and reaps the child at exit, so a failing assertion leaves no station running::

    with station_spawn("run", "zero_offsets", ..., env=env) as proc:
        ...                              # wait for the journal, the emulator, a line on stdout
        proc.send_signal(signal.SIGTERM)
        r = proc.wait(timeout=30)        # a CliResult

``prelude``: Python run in the child before ``station.cli.main`` (it patches the station there: a fault hook, a
pause widening a write window); the child then runs the same ``main`` the console script runs.
"""

from __future__ import annotations

import contextlib
import io
import os
import select
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

# the console script installed next to this interpreter (make venv installs the project editable)
STATION = str(Path(sys.executable).with_name("station"))


class CliResult(NamedTuple):
    """What a run of ``station`` left behind; unpacks as ``code, out, err``."""

    code: int
    out: str
    err: str

    @property
    def err_lines(self) -> list[str]:
        return self.err.strip().splitlines()

    @property
    def errors(self) -> list[str]:
        """The ``station: error: ...`` lines on stderr."""
        return [x for x in self.err.splitlines() if x.startswith("station: error:")]

    def error_line(self) -> str:
        """The one line a failure prints (asserts there is exactly one line on stderr)."""
        lines = self.err_lines
        assert len(lines) == 1, f"expected one line on stderr, got {len(lines)}:\n{self.err}"
        return lines[0]


def _exit_code(e: SystemExit) -> int:
    # sys.exit("text") prints the text and exits 1, as the interpreter does
    if e.code is None:
        return 0
    return e.code if isinstance(e.code, int) else 1


def station_main(*args, env: Mapping[str, str] | None = None, cwd: str | Path | None = None,
                 columns: int | None = None) -> CliResult:
    """``station ARGS`` in this process through ``station.cli.main``. ``env`` is laid over ``os.environ`` (and
    restored), ``cwd`` is entered (and left), ``columns`` sets ``COLUMNS`` (rich/click wrap to it)."""
    from station.cli import main

    extra = dict(env or {})
    if columns is not None:
        extra["COLUMNS"] = str(columns)
    out, err = io.StringIO(), io.StringIO()
    saved_argv, saved_env = sys.argv, dict(os.environ)
    sys.argv = ["station", *map(str, args)]
    os.environ.update(extra)
    # click names the program after ``__main__``'s package when there is one ("python -m pytest"); the console
    # script has none, so its messages say "station ...": the same here
    main_module = sys.modules.get("__main__")
    saved_package = getattr(main_module, "__package__", None)
    if main_module is not None:
        main_module.__package__ = None
    code = 0
    try:
        with contextlib.ExitStack() as stack:
            if cwd is not None:
                stack.enter_context(contextlib.chdir(cwd))
            stack.enter_context(contextlib.redirect_stdout(out))
            stack.enter_context(contextlib.redirect_stderr(err))
            try:
                main()
            except SystemExit as e:
                code = _exit_code(e)
    finally:
        sys.argv = saved_argv
        os.environ.clear()
        os.environ.update(saved_env)
        if main_module is not None:
            main_module.__package__ = saved_package
    return CliResult(code, out.getvalue(), err.getvalue())


# what the console script does, after a prelude has patched the station in the child
_MAIN = "import sys\nsys.argv[0] = 'station'\nfrom station.cli import main\nmain()\n"


def _command(args, module: bool, prelude: str | None) -> list[str]:
    if prelude is not None:
        return [sys.executable, "-c", f"{prelude}\n{_MAIN}", *map(str, args)]
    cmd = [sys.executable, "-m", "station.cli"] if module else [STATION]
    return [*cmd, *map(str, args)]


def _env(env: Mapping[str, str] | None, replace_env: bool) -> dict[str, str]:
    return dict(env or {}) if replace_env else {**os.environ, **(env or {})}


def station_proc(*args, env: Mapping[str, str] | None = None, cwd: str | Path | None = None,
                 timeout: float = 180, module: bool = False, stdin: str | None = None,
                 replace_env: bool = False, prelude: str | None = None) -> CliResult:
    """``station ARGS`` as a child process: the installed console script, or ``python -m station.cli`` with
    ``module=True``, or ``main`` after ``prelude`` (Python source run first in the child). ``env`` is laid over
    ``os.environ`` (``replace_env=True``: used as the whole environment); ``stdin`` is fed to the command
    (default: no input, never the terminal)."""
    p = subprocess.run(_command(args, module, prelude), capture_output=True, text=True, timeout=timeout, cwd=cwd,
                       env=_env(env, replace_env), input=stdin,
                       stdin=None if stdin is not None else subprocess.DEVNULL)
    return CliResult(p.returncode, p.stdout, p.stderr)


class ChildProcess:
    """A child started by ``station_spawn`` or ``python_spawn``, still running: signal it, read its stdout line by
    line, wait for its ``CliResult``. A context manager: a child still running at exit is killed and reaped."""

    def __init__(self, cmd: list[str], *, env: dict[str, str], cwd: str | Path | None) -> None:
        # stdout: bytes, read here line by line (a line waited for with a timeout is never stuck in a text
        # buffer); stderr: a file, so a long-lived child that logs a lot never blocks on a full pipe nobody reads
        self._err = tempfile.TemporaryFile()  # noqa: SIM115 - closed in close()
        self.popen = subprocess.Popen(cmd, env=env, cwd=cwd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                      stderr=self._err)
        self._buf = b""
        self._closed = False

    @property
    def pid(self) -> int:
        return self.popen.pid

    @property
    def returncode(self) -> int | None:
        """The exit code once it ended (``-N``: killed by signal N), else None."""
        return self.popen.poll()

    def running(self) -> bool:
        return self.popen.poll() is None

    def send_signal(self, sig: int) -> None:
        self.popen.send_signal(sig)

    def kill(self) -> None:
        """SIGKILL: no teardown runs in the child."""
        self.popen.kill()

    def readline(self, timeout: float | None = None) -> str:
        """The next line the child prints, with its newline; "" at the end of its output or, with ``timeout``,
        when no whole line came within it."""
        end = None if timeout is None else time.monotonic() + timeout
        fd = self.popen.stdout.fileno()
        while b"\n" not in self._buf:
            left = None if end is None else max(0.0, end - time.monotonic())
            if not select.select([fd], [], [], left)[0]:
                return ""
            chunk = os.read(fd, 4096)
            if not chunk:
                break
            self._buf += chunk
        line, sep, self._buf = self._buf.partition(b"\n")
        return (line + sep).decode(errors="replace")

    def wait(self, timeout: float = 180) -> CliResult:
        """Wait for the end (``subprocess.TimeoutExpired`` past ``timeout``); what the child left: exit code, the
        rest of stdout (after the lines read), stderr."""
        out, _ = self.popen.communicate(timeout=timeout)
        rest, self._buf = self._buf + (out or b""), b""
        return CliResult(self.popen.returncode, rest.decode(errors="replace"), self.stderr())

    def stderr(self) -> str:
        """What the child wrote to stderr so far."""
        self._err.seek(0)
        return self._err.read().decode(errors="replace")

    def close(self) -> None:
        """Kill the child if it still runs and reap it (safe to call twice)."""
        if self._closed:
            return
        self._closed = True
        if self.popen.poll() is None:
            self.popen.kill()
        self.popen.communicate()
        self._err.close()

    def __enter__(self) -> ChildProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def station_spawn(*args, env: Mapping[str, str] | None = None, cwd: str | Path | None = None,
                  module: bool = False, prelude: str | None = None, replace_env: bool = False) -> ChildProcess:
    """``station ARGS`` started as a child process and left running (as ``station_proc`` starts it); stdin is
    empty, stdout and stderr are read through the ``ChildProcess``."""
    return ChildProcess(_command(args, module, prelude), env=_env(env, replace_env), cwd=cwd)


def python_spawn(code: str, *args, env: Mapping[str, str] | None = None,
                 cwd: str | Path | None = None) -> ChildProcess:
    """``python -c CODE ARGS`` started as a child process (unbuffered output): a script that opens a robot through
    the station's API, for a test that needs the station in a second process it can stop or kill (a host that
    does not schedule it, a station killed mid-move) where no command does what the script does."""
    return ChildProcess([sys.executable, "-c", code, *map(str, args)],
                        env=_env({"PYTHONUNBUFFERED": "1", **(env or {})}, False), cwd=cwd)
