"""``station.plugins``: the one entry-point registry, library-import wrapping and close-once lifecycle that robot
drivers, measuring instruments and emulators share; and ``station.lazy.lazy_exports``, their packages' lazy names.
Real entry points (the installed station's groups) and real packages written to a temporary folder."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from importlib.metadata import EntryPoint

import pytest
from station.mocks import plug as plug_module

from station.lazy import lazy_exports
from station.plugins import CloseOnce, Registry, library
from station.robot.registry import REGISTRY as ROBOTS


class Refused(Exception):
    pass


def _registry(entries: dict[str, EntryPoint], **kw) -> Registry:
    reg = Registry("test.group", "widget", Refused, **kw)
    reg._entries = {reg._key(name): ep for name, ep in entries.items()}  # as read from importlib.metadata
    return reg


@pytest.fixture
def widgets(tmp_path, monkeypatch):
    """A package with a plug, one whose library is missing and one whose own station module is missing."""
    (tmp_path / "widgetpkg.py").write_text(textwrap.dedent('''
        class Widget:
            pass
    '''))
    (tmp_path / "needsfoo.py").write_text("import foo_library_not_installed\n")
    (tmp_path / "needsstation.py").write_text("import station.no_such_module\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    return {name: EntryPoint(name=name, value=value, group="test.group") for name, value in (
        ("Good", "widgetpkg:Widget"), ("foo", "needsfoo:X"), ("bug", "needsstation:X"))}


def test_registry_loads_by_name_and_refuses_in_one_line(widgets):
    reg = _registry(widgets)
    assert reg.names() == ["bug", "foo", "good"]  # URL schemes compare case-blind
    assert reg.load("GOOD").__name__ == "Widget"
    with pytest.raises(Refused, match=r"^unknown scheme 'nope'; known: bug, foo, good$"):
        reg.load("nope")
    with pytest.raises(Refused, match=r"^the foo widget \(needsfoo:X\) needs the Python module "
                                      r"'foo_library_not_installed', which is not installed$"):
        reg.load("foo")
    with pytest.raises(ModuleNotFoundError, match="station.no_such_module"):  # our own bug: its traceback
        reg.load("bug")


def test_registry_empty_group_and_case_kept(widgets):
    assert _registry({}).names() == []
    with pytest.raises(Refused, match=r"^unknown scheme 'x'; known: none$"):
        _registry({}).entry("x")
    with pytest.raises(Refused, match=r"^nothing is installed$"):
        _registry({}, empty="nothing is installed").entry("x")
    reg = _registry({"Good": widgets["Good"]}, fold_case=False, noun="bus")
    assert reg.names() == ["Good"]
    with pytest.raises(Refused, match=r"^unknown bus 'good'; known: Good$"):
        reg.entry("good")


def test_the_three_groups_are_read_from_the_installed_entry_points():
    assert {"dynamixel", "ur", "canopen+virtual"} <= set(ROBOTS.names())
    assert ROBOTS.entry("UR").group == "station.robots"
    assert "tracker" in plug_module.REGISTRY.names() and "canopen" in plug_module.plugs()
    from station.instruments.registry import REGISTRY as INSTRUMENTS

    assert INSTRUMENTS.names() == ["tcp"] and INSTRUMENTS.group == "station.instruments"


def test_an_emulator_plug_without_its_library_is_one_line(widgets, monkeypatch):
    monkeypatch.setattr(plug_module.REGISTRY, "_entries", {"foo": widgets["foo"]})
    monkeypatch.setattr(plug_module, "_PLUGS", None)
    with pytest.raises(plug_module.MockError, match=r"^the foo emulator \(needsfoo:X\) needs the Python module"):
        plug_module.plugs()
    monkeypatch.setattr(plug_module, "_PLUGS", None)


def test_library_names_the_package_to_install():
    refused = r"^the Python package foo-lib is not installed \(import of 'foo_library_not_installed' failed\); " \
              r"install it: pip install foo-lib$"
    with pytest.raises(Refused, match=refused), library("foo-lib", Refused):
        import foo_library_not_installed  # noqa: F401
    with pytest.raises(ModuleNotFoundError), library("x", Refused):
        import station.no_such_module  # noqa: F401
    with library("numpy", Refused):
        import numpy  # noqa: F401  (present: nothing happens)


class Link(CloseOnce):
    noun = "link"
    closed_error = ConnectionError

    def __init__(self, fail: bool = False) -> None:
        self.shutdowns = 0
        if fail:
            raise OSError("half built")
        self.url = "link://a"

    def _shutdown(self) -> None:
        self.shutdowns += 1

    def use(self) -> str:
        self._check_open("use")
        return "ok"


def test_close_once_lifecycle():
    with Link() as link:
        assert link.use() == "ok" and not link.closed and repr(link) == "<Link link://a>"
    assert link.closed and link.shutdowns == 1 and repr(link) == "<Link link://a closed>"
    link.close()
    assert link.shutdowns == 1
    with pytest.raises(ConnectionError, match=r"^use: link://a is closed; open the link again$"):
        link.use()
    half = Link.__new__(Link)  # a constructor that failed before setting anything
    half.shutdowns = 0
    half.close()
    assert half.closed and half.shutdowns == 1 and repr(half) == "<Link ? closed>"


LAZY = """
import sys, types
from station.lazy import lazy_exports
pkg = types.ModuleType("pkg"); sys.modules["pkg"] = pkg
pkg.__all__, pkg.__getattr__, pkg.__dir__ = lazy_exports("pkg", {"station.textfile": ("read_capped",)})
print(pkg.__all__, "station.textfile" in sys.modules, "read_capped" in pkg.__dir__())
print(pkg.read_capped.__module__, "read_capped" in vars(pkg))
"""


def test_lazy_exports_in_a_fresh_interpreter():
    p = subprocess.run([sys.executable, "-c", LAZY], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    assert p.stdout.splitlines() == ["['read_capped'] False True", "station.textfile True"]
    all_, getattr_, _ = lazy_exports("station.textfile", {"station.textfile": ("read_capped",)})
    with pytest.raises(AttributeError, match="has no attribute 'nope'"):
        getattr_("nope")
