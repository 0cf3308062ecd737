"""docs/cli.md against the CLI's own help, and one style for every ``--help``: the generated command reference
is what the CLI says now, every option the hand-written sections name exists, every command and option has
help in the same style, group listings show whole first lines (never cut with "..."), ``run --help`` names
every shipped procedure, every emulator stops with its parent."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from clirunner import station_main

from station.cli import COMMANDS
from station.cli.docgen import commands, current_block, reference
from station.cli.helpgroup import first_sentence

DOC = Path(__file__).resolve().parents[2] / "docs" / "cli.md"
OWN_STYLE_EXEMPT = ("station jog",)  # the jog UI's options are the jog UI's (docs/jog.md); checked there


def _help(*args: str, columns: int = 80) -> str:
    return station_main(*args, "--help", columns=columns).out


def _flat(text: str) -> str:
    return " ".join(text.split())


@pytest.fixture(scope="module")
def tree():
    return commands()


def test_docs_command_reference_is_generated_from_the_cli():
    block = current_block(DOC.read_text())
    assert block is not None, "docs/cli.md lost its generated command reference"
    assert block == reference(), "docs/cli.md differs from the CLI: python -m station.cli.docgen --write docs/cli.md"


def test_every_option_the_docs_name_exists(tree):
    text = DOC.read_text()
    hand = text.split(current_block(text) or "\0")[0]
    flags = {o for _, c in tree for p in c.params for o in [*getattr(p, "opts", []), *getattr(p, "secondary_opts", [])]}
    flags.add("--help")  # every command has it (click's own, not among its params)
    named = set(re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]+)", hand))
    assert not named - flags, f"docs/cli.md names options no command has: {sorted(named - flags)}"
    for name in COMMANDS:
        assert re.search(rf"^## .*\bstation {name}\b", hand, re.M), f"docs/cli.md has no section for station {name}"


def test_one_help_style(tree):
    bad = []
    for path, c in tree:
        if not (c.help or "").strip():
            bad.append(f"{path}: no help")
        if path.startswith(OWN_STYLE_EXEMPT):
            continue
        for p in c.params:
            if p.name == "help":
                continue
            h = (getattr(p, "help", None) or "").strip()
            if not h:
                bad.append(f"{path} {p.name}: no help")
            elif not (h[0].isupper() or h[0].isdigit() or re.match(r"^[a-z][\w.]*[:,]", h)):
                bad.append(f"{path} {p.name}: help starts in lower case: {h[:40]!r}")
            elif "..." in h.replace("..N", "").replace("...", "", h.count("Q1,Q2,...")):
                bad.append(f"{path} {p.name}: help is cut: {h[:40]!r}")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("group", ["", "map", "model", "records", "mock", "mock world"])
def test_group_help_lists_whole_first_lines(tree, group):
    text = _help(*group.split()).split("Commands:", 1)[-1]
    assert "..." not in text, text
    flat = _flat(text)
    prefix = f"station {group}".strip()
    for path, c in tree:
        if path.rsplit(" ", 1)[0] == prefix:
            line = first_sentence(COMMANDS[path.split()[1]][1] if not group else (c.short_help or c.help))
            assert _flat(line) in flat, (path, line)


def test_run_help_lists_every_shipped_procedure():
    from station.engine.procedure import shipped_names

    flat = _flat(_help("run", columns=200))
    for name in shipped_names():
        assert name in flat, name
    assert "correction_map" in flat and "--identify" in flat


def test_model_list_and_the_docs_agree():
    from station.kinematics import builtin_names

    r = station_main("model", "list")
    assert r.code == 0, r.err
    listed = [ln.split()[0] for ln in r.out.splitlines() if ln.strip()]
    assert listed == list(builtin_names())
    documented = re.findall(r"^\| `([a-z0-9]+)` \| \d+ \|", current_block(DOC.read_text()), re.M)
    assert documented == listed


def test_every_emulator_stops_with_its_parent(tree):
    emulators = [c for path, c in tree if re.fullmatch(r"station mock (ur|dynamixel|canopen)", path)]
    assert len(emulators) == 3
    for c in emulators:
        assert any("--exit-with-parent" in getattr(p, "opts", []) for p in c.params), c.name
