"""``station solve``/``fk`` are plain click commands, the other commands typer (start-up: bench/startup.py); an option
is declared once (``station.cli.optspec.Opt``) and made into either. The same argv parsed both ways must give the
same values, and the same kind of refusal: the typer twin here is built from the very declarations."""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest

from station.cli.model_options import MODEL_OPTIONS
from station.cli.optspec import REQUIRED
from station.cli.solve_cmd import FK_OPTIONS, SOLVE_OPTIONS, fk_command, solve_command


def typer_values(options, argv: list[str]):
    """What typer hands the callback for ``argv``, with options made by ``Opt.typer()``; or the usage error."""
    import typer
    from typer.main import get_command

    got: dict = {}

    def callback(**kw):
        got.update(kw)

    callback.__signature__ = inspect.Signature([
        inspect.Parameter(o.name, inspect.Parameter.KEYWORD_ONLY, default=o.typer(),
                          annotation=list[o.kind] if o.multiple else o.kind) for o in options])
    app = typer.Typer(rich_markup_mode=None)
    app.command()(callback)
    try:
        get_command(app).main(argv, prog_name="station x", standalone_mode=False)
    except Exception as e:  # a usage error of typer's click
        return type(e).__name__
    return {k: tuple(v or ()) if isinstance(v, list | tuple) or v is None and _multiple(options, k) else v
            for k, v in got.items()}


def click_values(options, argv: list[str]):
    """What the click command made by ``Opt.click()`` hands its callback for ``argv``; or the usage error."""
    from station.cli.optspec import click_command

    got: dict = {}

    def callback(**kw):
        """Test."""
        got.update(kw)

    try:
        click_command("x", callback, options).main(argv, prog_name="station x", standalone_mode=False)
    except Exception as e:  # a usage error of click
        return type(e).__name__
    return got


def _multiple(options, name: str) -> bool:
    return next(o for o in options if o.name == name).multiple


SAME = [
    (SOLVE_OPTIONS, ["--model", "ur5e", "--samples", "s.csv"]),
    (SOLVE_OPTIONS, ["--model", "m.yaml", "--samples", "dir/s.csv", "--identify", "offsets,tcp,dh", "--reference",
                     "A=1,2,3mm", "--reference", "B=0,0,0", "--tool", "0,0,120mm", "--holdout", "h.csv", "--out",
                     "r.json", "--instrument-frame", "base", "--max-std", "2e-4", "--prior", "offsets=0.5deg",
                     "--prior", "dh=0.3mm", "--noise", "20um", "--loss", "huber", "--distance", "A,B=50mm",
                     "--plane", "P", "--payload", "0.5kg@0,0,30mm"]),
    (SOLVE_OPTIONS, ["--samples=s.csv", "--model=arm.urdf", "--tip-link", "tool0", "--base-link", "base",
                     "--max-std=1"]),
    (FK_OPTIONS, ["--model", "ur5e", "--joints", "q.csv"]),
    (FK_OPTIONS, ["--model", "ur5e", "--joints", "q.csv", "--calibration", "r.json", "--tool", "1,2,3", "--out",
                  "o.csv"]),
]
REFUSED = [
    (SOLVE_OPTIONS, ["--samples", "s.csv"], "MissingParameter"),
    (SOLVE_OPTIONS, ["--model", "ur5e"], "MissingParameter"),
    (FK_OPTIONS, ["--model", "ur5e", "--joints", "j.csv", "--calibration"], "BadOptionUsage"),
    (SOLVE_OPTIONS, ["--model", "ur5e", "--samples", "s.csv", "--max-std"], "BadOptionUsage"),
    (SOLVE_OPTIONS, ["--model", "ur5e", "--samples", "s.csv", "--modle", "x"], "NoSuchOption"),
    (SOLVE_OPTIONS, ["--model", "ur5e", "--samples", "s.csv", "extra"], "UsageError"),
    (FK_OPTIONS, ["--model", "ur5e"], "MissingParameter"),
]


@pytest.mark.parametrize(("options", "argv"), SAME)
def test_the_same_argv_gives_the_same_values_through_click_and_typer(options, argv):
    by_click, by_typer = click_values(options, argv), typer_values(options, argv)
    assert isinstance(by_click, dict), by_click
    assert by_click == by_typer
    assert set(by_click) == {o.name for o in options}
    for o in options:  # the declared kinds, not strings: a Path is a Path, a float a float
        v = by_click[o.name]
        if o.multiple:
            assert isinstance(v, tuple) and all(isinstance(x, o.kind) for x in v)
        elif v is not None:
            assert isinstance(v, o.kind)
        else:
            assert o.default is None


@pytest.mark.parametrize(("options", "argv", "error"), REFUSED)
def test_the_same_bad_argv_is_refused_alike(options, argv, error):
    by_click, by_typer = click_values(options, argv), typer_values(options, argv)
    assert by_click == by_typer == error


def test_the_commands_take_exactly_their_declared_options():
    """Every declared option is a parameter of the command's function and nothing else is."""
    for options, fn in ((SOLVE_OPTIONS, solve_command), (FK_OPTIONS, fk_command)):
        assert [o.name for o in options] == list(inspect.signature(fn).parameters)
        assert options[:len(MODEL_OPTIONS)] == MODEL_OPTIONS
        assert len({o.flag for o in options}) == len(options)


def test_help_shows_each_declared_help_once_as_typer_prints_it():
    from station.cli.optspec import click_command

    text = click_command("solve", solve_command, SOLVE_OPTIONS).get_help(_ctx(SOLVE_OPTIONS))
    flat = " ".join(text.split())
    for o in SOLVE_OPTIONS:
        assert " ".join(o.help.split()) in flat
    assert "--model <str>" in text and "--samples <path>" in text and "--max-std <str>" in text
    assert flat.count("[required]") == sum(o.default is REQUIRED for o in SOLVE_OPTIONS)
    assert "[default: offsets,tcp]" in flat


def _ctx(options):
    import click

    from station.cli.optspec import click_command

    return click.Context(click_command("solve", solve_command, options), info_name="station solve")


def test_a_path_option_is_not_checked_by_click(tmp_path):
    """A file that is missing or unreadable is the command's to report (naming it, one line), not click's."""
    missing = tmp_path / "nope.csv"
    got = click_values(FK_OPTIONS, ["--model", "ur5e", "--joints", str(missing)])
    assert got["joints"] == Path(missing)


def test_the_typer_group_still_runs_the_click_commands(tmp_path):
    """``station.cli.app`` (used directly by scripts and tests) hands ``solve``/``fk`` their arguments unparsed."""
    from typer.testing import CliRunner

    from station.cli import app

    joints = tmp_path / "q.csv"
    joints.write_text("q1[deg],q2[deg],q3[deg],q4[deg],q5[deg],q6[deg]\n0,-90,90,-90,-90,0\n10,-80,70,-90,-90,0\n")
    r = CliRunner().invoke(app, ["fk", "--model", "ur5e", "--joints", str(joints)])
    assert r.exit_code == 0, r.output
    assert len([x for x in r.output.splitlines() if x and not x.startswith(("#", "x["))]) == 2
    r = CliRunner().invoke(app, ["fk", "--model", "ur5e", "--joints", str(joints), "--modle", "x"])
    assert r.exit_code != 0 and type(r.exception).__name__ == "NoSuchOption"
