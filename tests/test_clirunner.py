"""The tests' one CLI runner (tests/clirunner.py): in process, as the console script and as ``python -m
station.cli``, the same command gives the same exit code and output; the environment and the working directory
given to the in-process runner are restored afterwards."""

from __future__ import annotations

import os

from clirunner import CliResult, station_main, station_proc


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
