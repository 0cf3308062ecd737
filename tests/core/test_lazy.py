"""``station.lazy``: modules and package names imported on first use (what keeps ``station --help`` fast)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from station.lazy import lazy_module, lazy_names

CODE = """
import sys, types
from station.lazy import lazy_module, lazy_names
m = lazy_module("station.yamlfile")
assert "station.yamlfile" in sys.modules
print("before", "station.textfile" in sys.modules)       # the module body has not run: its imports neither
print(m.dotted(("a", 1, "b")))                           # first attribute: it runs
print("after", "station.textfile" in sys.modules)
print(lazy_module("station.yamlfile") is m)              # already imported: the same module
pkg = types.ModuleType("pkg"); sys.modules["pkg"] = pkg
pkg.__getattr__ = lazy_names("pkg", {"dotted": "station.textfile"})
print(pkg.dotted(("x", 2)), "dotted" in vars(pkg))      # resolved once, then an ordinary attribute
try:
    pkg.nothing
except AttributeError as e:
    print(e)
"""


def test_lazy_module_and_names_in_a_fresh_interpreter():
    p = subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    assert p.stdout.splitlines() == ["before False", "a[1].b", "after True", "True", "x[2] True",
                                     "module 'pkg' has no attribute 'nothing'"]


def test_in_this_process():
    import station.textfile

    assert lazy_module("station.textfile") is station.textfile  # already imported: no lazy stand-in
    getattr_ = lazy_names("station.textfile", {"read_capped": "station.textfile"})
    assert getattr_("read_capped") is station.textfile.read_capped
    with pytest.raises(AttributeError, match="has no attribute 'x'"):
        getattr_("x")
