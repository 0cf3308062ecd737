"""The one way tests run the ``station`` command: ``station_main`` in this process (the same ``main`` the installed
command runs; emulators on in-process buses stay reachable), ``station_proc`` as a child process (the installed
console script or ``python -m station.cli``: its own interpreter, exit path and environment). Both return a
``CliResult``: exit code, stdout, stderr.

    from clirunner import station_main, station_proc
    r = station_main("solve", "--model", "ur5e", "--samples", path)
    assert r.code == 2 and r.error_line().startswith("station: error: ")
"""

from __future__ import annotations

import contextlib
import io
import os
import subprocess
import sys
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


def station_proc(*args, env: Mapping[str, str] | None = None, cwd: str | Path | None = None,
                 timeout: float = 180, module: bool = False, stdin: str | None = None,
                 replace_env: bool = False) -> CliResult:
    """``station ARGS`` as a child process: the installed console script, or ``python -m station.cli`` with
    ``module=True``. ``env`` is laid over ``os.environ`` (``replace_env=True``: used as the whole environment);
    ``stdin`` is fed to the command (default: no input, never the terminal)."""
    cmd = [sys.executable, "-m", "station.cli"] if module else [STATION]
    full_env = dict(env or {}) if replace_env else {**os.environ, **(env or {})}
    p = subprocess.run([*cmd, *map(str, args)], capture_output=True, text=True, timeout=timeout, cwd=cwd,
                       env=full_env, input=stdin, stdin=None if stdin is not None else subprocess.DEVNULL)
    return CliResult(p.returncode, p.stdout, p.stderr)
