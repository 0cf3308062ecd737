"""House rule: the tests run the ``station`` command one way, through tests/clirunner.py (``station_main`` in
process; ``station_proc`` / ``station_spawn`` as a child process; ``python_spawn`` for a script that needs a
process of its own). A test file that starts the command itself (``subprocess.run``/``Popen`` on the console
script, ``python -m station.cli`` or code that imports ``station.cli``) or calls ``station.cli.main`` directly
fails here, unless it is listed below with the reason the one runner cannot serve it.

``python tests/test_one_runner.py`` lists every offending call with its file and line."""

from __future__ import annotations

import ast
import re
from pathlib import Path

TESTS = Path(__file__).resolve().parent

# the runner itself
RUNNER = {"clirunner.py"}

# file (relative to tests/) -> why it starts the station its own way
ALLOWED = {
    # the command on a real terminal (a pty the test reads and types into): clirunner's pipes are not a tty
    "tui/test_tui_terminal.py": "the command runs on a pty the test reads as a terminal",
    "tui/test_jog_keys.py": "the command runs on a pty the test types keys into",
    # what is tested is how the command starts, not what it does
    "cli/test_startup.py": "lists the modules main loaded (code after main), writes stdout to /dev/full, and "
                           "checks main itself leaves gc and the environment as found (station_main restores them)",
    "cli/test_wheel_install.py": "the console script of a wheel installed into a fresh virtual environment",
}

SUBPROCESS_CALLS = {"run", "Popen", "call", "check_call", "check_output"}
# what in a command line (resolved through the module's own assignments) means "the station command"
STATION = re.compile(r"""station\.cli|with_name\(\s*['"]station['"]\s*\)|/\s*['"]station['"]|['"]station['"]\s*[,\]]""")


def _assignments(tree: ast.AST) -> dict[str, list[ast.AST]]:
    """Every name's assigned values, in any scope of the module."""
    out: dict[str, list[ast.AST]] = {}
    for node in ast.walk(tree):
        targets, value = [], None
        if isinstance(node, ast.Assign):
            targets, value = node.targets, node.value
        elif isinstance(node, ast.AnnAssign) and node.value is not None or isinstance(node, ast.NamedExpr):
            targets, value = [node.target], node.value
        for t in targets:
            for name in ast.walk(t):
                if isinstance(name, ast.Name):
                    out.setdefault(name.id, []).append(value)
    return out


def _resolved(node: ast.AST, assigned: dict[str, list[ast.AST]], depth: int = 2) -> str:
    """The source of ``node`` with the values of the names it uses, followed through ``depth`` assignments (a
    command list naming ``CLI``, whose value names ``CODE``; deeper is what the command is about, not what runs
    it)."""
    text, seen, todo = [], set(), [(node, 0)]
    while todo:
        top, level = todo.pop()
        text.append(ast.unparse(top))
        if level == depth:
            continue
        # an attribute's owner (``term`` in ``term.sock``) is not followed: its value is not the command
        owners = {id(a.value) for a in ast.walk(top) if isinstance(a, ast.Attribute)}
        for sub in ast.walk(top):
            if isinstance(sub, ast.Name) and sub.id not in seen and id(sub) not in owners:
                seen.add(sub.id)
                todo.extend((value, level + 1) for value in assigned.get(sub.id, []))
    return "\n".join(text)


def _subprocess_names(tree: ast.AST) -> tuple[set[str], set[str]]:
    """(module aliases of subprocess, bare names imported from it that start processes)."""
    modules, bare = set(), set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            modules |= {a.asname or a.name for a in node.names if a.name == "subprocess"}
        elif isinstance(node, ast.ImportFrom) and node.module == "subprocess":
            bare |= {a.asname or a.name for a in node.names if a.name in SUBPROCESS_CALLS}
    return modules, bare


def offences(source: str, name: str = "<test>") -> list[str]:
    """``FILE:LINE: what`` for every way ``source`` starts the station outside the one runner."""
    if "subprocess" not in source and "station.cli" not in source:  # neither way is open to it
        return []
    tree = ast.parse(source)
    assigned = _assignments(tree)
    modules, bare = _subprocess_names(tree)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module == "station.cli" and any(
                a.name == "main" for a in node.names):
            found.append(f"{name}:{node.lineno}: imports station.cli.main (run it with clirunner.station_main)")
        elif isinstance(node, ast.Attribute) and node.attr == "main" and \
                ast.unparse(node.value).endswith("station.cli"):
            found.append(f"{name}:{node.lineno}: calls station.cli.main (run it with clirunner.station_main)")
        elif isinstance(node, ast.Call):
            f = node.func
            starts = (isinstance(f, ast.Attribute) and f.attr in SUBPROCESS_CALLS and isinstance(f.value, ast.Name)
                      and f.value.id in modules) or (isinstance(f, ast.Name) and f.id in bare)
            cmd = node.args[0] if node.args else next((k.value for k in node.keywords if k.arg == "args"), None)
            if starts and cmd is not None and STATION.search(_resolved(cmd, assigned)):
                found.append(f"{name}:{node.lineno}: starts the station with subprocess "
                             "(clirunner.station_proc / station_spawn)")
    return found


def _files() -> list[Path]:
    return sorted(p for p in TESTS.rglob("*.py") if p.relative_to(TESTS).as_posix() not in RUNNER)


def test_the_checker_finds_each_way_and_passes_the_runner():
    own = [
        'import subprocess, sys\nsubprocess.run([sys.executable, "-m", "station.cli", "solve"])\n',
        'import subprocess, sys\nCLI = "from station.cli import main; main()"\n'
        'def f(args):\n    return subprocess.Popen([sys.executable, "-c", CLI, *args])\n',
        'from subprocess import run\nfrom pathlib import Path\nimport sys\n'
        'STATION = str(Path(sys.executable).with_name("station"))\nrun([STATION, "demo"])\n',
        'import subprocess as sp\nsp.check_output([env / "bin" / "station", "demo"])\n',
        'def t():\n    from station.cli import main\n    main()\n',
        'import station.cli\nstation.cli.main()\n',
    ]
    for src in own:
        assert offences(src), src
    fine = [
        'from clirunner import station_proc\nstation_proc("demo", "--robot", "ur")\n',
        'import subprocess\nsubprocess.run(["tmux", "kill-server"])\n',
        'import subprocess, sys\nsubprocess.run([sys.executable, "-c", "import station.kinematics"])\n',
        'from station.cli import COMMANDS\n',
    ]
    for src in fine:
        assert not offences(src), src


def test_no_test_starts_the_station_outside_the_one_runner():
    found = []
    for path in _files():
        rel = path.relative_to(TESTS).as_posix()
        if rel not in ALLOWED:
            found += offences(path.read_text(), rel)
    assert not found, "start the station through tests/clirunner.py:\n" + "\n".join(found)


def test_every_exception_is_still_needed():
    """An allow-list entry whose file no longer starts the station its own way (or is gone) is dropped."""
    stale = [rel for rel in ALLOWED if not (TESTS / rel).is_file() or not offences((TESTS / rel).read_text(), rel)]
    assert not stale, f"no longer needed in ALLOWED: {stale}"


if __name__ == "__main__":
    for p in _files():
        for line in offences(p.read_text(), p.relative_to(TESTS).as_posix()):
            print(line + ("  [allowed]" if p.relative_to(TESTS).as_posix() in ALLOWED else ""))
