"""``station records`` tables at 80 and 160 columns (rich's console width set through COLUMNS): no line wider
than the terminal, no number split across lines or cut, no header wrapped, reasons whole (wrapped at words, never
cut mid-word); the CSV export names each session's model."""

from __future__ import annotations

import csv
import io
import math
import re

import pytest
from clirunner import station_main

from station.records import open_records
from tests.records.test_records_cli_questions import LONG, _shifted


@pytest.fixture
def stored(tmp_path, session_factory):
    url = f"sqlite:///{tmp_path / 'station.db'}"
    last = _shifted(session_factory(seed=3, serial=LONG)[0], "offset.j2", 20.0, seed=4)
    last["result"]["parameters"]["offset.j1"].update(
        identifiable=False, value=None, std=None,
        reason="a rotation about joint 1 moves the unknown point with the robot: these poses cannot tell it "
               "from the point's position, whatever their spread")
    with open_records(url) as rec:
        rec.store_session(session_factory(seed=3, serial=LONG)[0])
        rec.store_session(last)
        return url, rec.session(last["session"])


def _shown(*args: str, columns: int) -> str:
    result = station_main(*args, columns=columns)
    assert result.code == 0, result.err
    return result.out


def _flat(text: str) -> str:
    return " ".join(text.split())


@pytest.mark.parametrize("columns", [80, 160])
def test_show_keeps_numbers_headers_and_reasons_whole(stored, columns):
    url, session = stored
    out = _shown("records", "show", LONG, "--db", url, columns=columns)
    lines = out.splitlines()
    assert max(len(x) for x in lines) <= columns, out
    assert "…" not in out  # nothing cut with an ellipsis
    params = session["result"]["parameters"]
    for name, p in params.items():
        if p.get("kind") == "point" or not p["identifiable"]:
            continue
        k = math.degrees(1) if p["unit"] == "rad" else 1e3
        row = next(x for x in lines if re.match(rf"[\s│┃]*{re.escape(name)}\s", x))
        for v in (p["value"], p["std"]):  # the estimate and its sigma, whole, on the parameter's own line
            assert re.search(rf"(?<![\d.]){re.escape(f'{v * k:.4f}')}(?![\d])", row), (name, row)
    reason = params["offset.j1"]["reason"]
    if columns < 120:  # below the table, wrapped at words: the words and their order survive
        assert _flat(reason) in _flat(out), out
    for word in reason.split():  # in a table cell: wrapped at words, none cut

        assert re.search(rf"(?<!\S){re.escape(word)}(?!\S)", out), word
    verdict = {m["name"]: m for m in session["verdict"]["measurements"]}
    below = lines[next(i for i, x in enumerate(lines) if x.startswith("Verdict")):]
    for name, m in verdict.items():
        if m.get("value") is not None:
            row = next(x for x in below if re.match(rf"[\s│┃]*{re.escape(name)}\s", x))
            assert f"{float(m['value']):.4g}" in row, (name, row)
    headers = ["session", "samples", "rms after mm", "verdict"] + (["rms before mm", "procedure"] if columns >= 120
                                                                    else [])
    head = next(x for x in lines if "session" in x and "samples" in x)
    for h in headers:
        assert h in head, (h, head)  # one header line: never wrapped


@pytest.mark.parametrize("columns", [80, 160])
def test_list_and_trend_fit_and_keep_numbers(stored, columns):
    url, session = stored
    for args in (("records", "list", "--db", url), ("records", "list", "--db", url, "--serial", LONG),
                 ("records", "show", LONG, "--db", url, "--trend")):
        out = _shown(*args, columns=columns)
        assert max(len(x) for x in out.splitlines()[1:]) <= columns, out
        assert "…" not in out.split("\n", 1)[1], out
    out = _shown("records", "show", LONG, "--db", url, "--trend", columns=columns)
    p = session["result"]["parameters"]["offset.j2"]
    row = next(x for x in out.splitlines() if "DRIFT" in x)
    assert f"{math.degrees(p['value']):.4f}" in row and f"{math.degrees(p['std']):.4f}" in row, out


def test_narrow_terminal_falls_back_to_one_block_per_session(stored):
    url, session = stored
    out = _shown("records", "list", "--db", url, "--serial", LONG, columns=50)
    assert max(len(x) for x in out.splitlines()[1:]) <= 50, out
    block = out.split(session["session"], 1)[1]
    assert re.search(r"^\s+verdict\s+PASS$", block, re.M) and re.search(r"^\s+samples\s+\d+$", block, re.M), out


def test_csv_export_names_the_model(stored):
    url, session = stored
    out = _shown("records", "export", "--format", "csv", "--db", url, columns=160)
    rows = list(csv.DictReader(io.StringIO(out)))
    assert rows and "model" in rows[0]
    assert {r["model"] for r in rows if r["session"] == session["session"]} == {session["model"]}


def test_trend_does_not_call_a_model_change_drift(tmp_path, session_factory):
    """Two arms filed under one serial (what a fixed emulator serial did): the second arm's values are no drift."""
    url = f"sqlite:///{tmp_path / 'station.db'}"
    first = session_factory(seed=3, serial=LONG)[0]
    other = _shifted(first, "offset.j2", 20.0, seed=5)
    other["model"] = "ur5e-other"
    with open_records(url) as rec:
        rec.store_session(first)
        rec.store_session(other)
    out = _shown("records", "show", LONG, "--db", url, "--trend", columns=160)
    assert "DRIFT" not in out and "model ur5e-other" in out, out
