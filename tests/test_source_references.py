"""Comments and docstrings point to what a reader can open: a docs/ page, a bench script, a vendor document, a
public issue tracker (``ur_rtde issue 527``) -- never to this team's issue numbers or internal seed files, which
a reader of the source does not have."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PARTS = ("station", "drivers", "mocks", "procedures", "bench", "tests")
# "issue 8", "Issue 15 item 6", "seed 004", "seed 003c" (a public project's issue is named with the project)
INTERNAL = re.compile(r"(?<![\w-])(?:[Ii]ssue\s?#?\d+|seed\s?0\d\d[a-z]?)\b")
PUBLIC = re.compile(r"(ur_rtde|python-can|canopen|libfranka|dynamixel|github)[^\n]{0,40}$", re.IGNORECASE)


def test_no_comment_names_an_internal_issue_or_seed():
    found = []
    for part in PARTS:
        for path in sorted(p for p in (ROOT / part).rglob("*.py") if p.name != Path(__file__).name):
            for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
                m = INTERNAL.search(line)
                if m and not PUBLIC.search(line[: m.start()]):
                    found.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    assert not found, "name the docs page or public source instead:\n" + "\n".join(found)
