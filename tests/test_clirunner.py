"""The tests' one CLI runner (tests/clirunner.py): in process, as the console script and as ``python -m
station.cli``, the same command gives the same exit code and output; the environment and the working directory
given to the in-process runner are restored afterwards; a spawned child is read, signalled and never left
running; a prelude patches the station in its child."""

from __future__ import annotations

import os
import signal

from clirunner import CliResult, python_spawn, station_main, station_proc, station_spawn


def test_the_three_ways_agree(tmp_path):
    bad = tmp_path / "s.csv"
    bad.write_text("q1,q2,q3,q4,q5,q6\n0,0,0,0,0,x\n")
    runs = [station_main("solve", "--model", "ur5e", "--samples", bad),
            station_proc("solve", "--model", "ur5e", "--samples", bad, timeout=60),
            station_proc("solve", "--model", "ur5e", "--samples", bad, timeout=60, module=True)]
    for r in runs:
        assert isinstance(r, CliResult) and r.code == 2 and r.out == ""
        assert r.error_line() == runs[0].error_line() and "s.csv:2" in r.errors[0]
    code, out, err = station_main("model", "list")  # unpacks as (code, out, err)
    assert code == 0 and "ur5e" in out and err == ""


def test_in_process_runs_leave_the_process_as_it_was(tmp_path):
    cwd, env = os.getcwd(), dict(os.environ)
    (tmp_path / "q.csv").write_text("q1,q2,q3,q4,q5,q6\n0,-1.57,0,-1.57,0,0\n")
    r = station_main("fk", "--model", "ur5e", "--joints", "q.csv", cwd=tmp_path,
                     env={"STATION_HOME": str(tmp_path / "home")}, columns=50)
    assert r.code == 0, r.err  # the relative path was found in the given directory
    assert os.getcwd() == cwd and dict(os.environ) == env


def test_usage_errors_name_the_command_as_the_console_script_does():
    inside = station_main("mock", "world", "example", "--nope")
    outside = station_proc("mock", "world", "example", "--nope", timeout=60)
    assert inside.code == outside.code == 2
    assert inside.error_line() == outside.error_line()
    assert inside.error_line().startswith("station: error: station mock world example: No such option: --nope")


def test_a_child_can_be_read_signalled_and_is_never_left_running(tmp_path):
    """``python_spawn``/``station_spawn``: a line waited for with a timeout, a signal, the exit code a signal
    gives; a child still running when the ``with`` block ends is killed and reaped."""
    code = "import sys, time\nprint('ready', sys.argv[1], flush=True)\ntime.sleep(60)\n"
    with python_spawn(code, "x") as child:
        assert child.readline(timeout=30) == "ready x\n" and child.readline(timeout=0.2) == ""  # nothing more yet
        child.send_signal(signal.SIGTERM)
        r = child.wait(timeout=10)
    assert r.code == -signal.SIGTERM and not child.running()
    with python_spawn(code, "y") as child:
        assert child.readline(timeout=30) == "ready y\n"
    assert child.returncode == -signal.SIGKILL  # killed at the end of the block
    with station_spawn("model", "list") as child:
        r = child.wait(timeout=60)
    assert r.code == 0 and "ur5e" in r.out and r.err == ""


def test_a_prelude_patches_the_station_in_its_child():
    """``prelude``: code run in the child before ``main``; the command then runs as the console script does."""
    r = station_proc("model", "list", prelude="print('patched first')", timeout=60)
    assert r.code == 0 and r.out.startswith("patched first\n") and "ur5e" in r.out
