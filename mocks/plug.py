"""The emulators' registry: the ``station.emulators`` entry-point group (python-can's interface registry idea).

Each entry names a :class:`Plug`, a small object that says what the station's own tools need to know about one
emulator, and imports nothing heavy: the ``station mock`` command registers every plug's command, the launcher
(``station.mocks.launch``) starts any of them for a world, ``station demo`` offers every plug with a demo world,
and the bus-conformance tests run their checks over every robot plug. A new bus (or instrument) plugs in with an
entry point of its own package, no edit here::

    [project.entry-points."station.emulators"]
    mybus = "mypackage.mock.plug:PLUG"

A plug's emulator is an :class:`station.mocks.emulator.EmulatorBase`; it runs in the caller's process
(``build``), or as ``station mock BUS`` in a child process that prints its robot URL (``child``), or both."""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from station.mocks.errors import MockError

from station.plugins import Registry

if TYPE_CHECKING:
    from station.mocks.emulator import EmulatorBase

GROUP = "station.emulators"
REGISTRY = Registry(GROUP, "emulator", MockError, noun="emulator", fold_case=False)  # bus names as written
IN_PROCESS, CHILD = "in-process", "child"


@dataclass(frozen=True)
class Demo:
    """What ``station demo --robot BUS`` runs: the model of the demo world and zero_offsets' options there."""

    model: str
    options: dict = field(default_factory=dict)  # procedure options (e.g. reference, cone_deg)
    query: str = ""  # extra robot URL options of the demo (e.g. a faster default speed)
    world: dict = field(default_factory=dict)  # world document keys set for the demo (e.g. a tool: the ball)
    sigma_deg: float = 0.15  # spread of the hidden joint zero errors


class Plug:
    """One emulator as the station's tools see it. Subclasses set the class attributes and override the hooks of
    the ways their emulator runs."""

    bus: str = ""  # `station mock BUS`, launch(BUS), station demo --robot BUS
    cli: str = ""  # module whose register(mock_app) adds the `station mock BUS` command
    kind: str = "robot"  # "robot" (opened with station.robot.open_robot) or "instrument" (open_instrument)
    modes: tuple[str, ...] = (IN_PROCESS,)  # how it can run; the first is launch()'s default
    ready_lines: int = 1  # child: the lines `station mock BUS` prints once it serves; the URL after "robot URL "
    default_model: str = ""  # the model of a default world when none is given
    demo: Demo | None = None

    def register(self, mock_app) -> None:
        """Add ``station mock BUS`` to the ``station mock`` group."""
        importlib.import_module(self.cli).register(mock_app)

    # ---- in this process ----------------------------------------------------------------------------------
    def build(self, world) -> EmulatorBase:
        """The emulator serving ``world`` in this process, configured by the world's ``buses.<bus>`` section
        (not started)."""
        raise MockError(f"the {self.bus} emulator does not run in-process")

    # ---- as `station mock BUS` in a child process --------------------------------------------------------------
    def child_args(self, emu) -> list[str]:
        """Options of ``station mock BUS`` for the launched emulator ``emu`` besides the world and
        ``--exit-with-parent`` (e.g. its loopback address, its serial number)."""
        return []

    def child_url(self, emu, lines: list[str]) -> str:
        """The robot URL from the child's ready lines (and what else they say, set on ``emu``)."""
        return lines[-1].rsplit("robot URL ", 1)[-1].strip()

    def power_cycle_child(self, emu) -> None:
        """Switch the emulated device in the child process off and on."""
        raise MockError(f"the {self.bus} emulator in a child process has no power cycle; run it in-process")

    # ---- the URL ---------------------------------------------------------------------------------------------
    def serial_in_url(self, emu) -> bool:
        """Whether the launcher adds ``&serial=`` to the URL (devices that report no serial of their own)."""
        return True


def _load() -> dict[str, Plug]:
    plugs: dict[str, Plug] = {}
    for name in REGISTRY.names():
        ep = REGISTRY.entry(name)
        try:
            plug = REGISTRY.load(name)
        except (ImportError, AttributeError) as e:  # our own module missing, or a missing name in it
            raise MockError(f"emulator {ep.name!r} ({ep.value}) cannot be imported: {e}") from None
        if not isinstance(plug, Plug) or plug.bus != ep.name:
            raise MockError(f"entry point {GROUP} {ep.name} = {ep.value} is not the Plug of bus {ep.name!r}")
        plugs[ep.name] = plug
    return plugs


_PLUGS: dict[str, Plug] | None = None


def plugs(kind: str | None = None) -> dict[str, Plug]:
    """Every registered plug by bus name (sorted), read from the entry points on first use; ``kind``: only
    robots or only instruments."""
    global _PLUGS
    if _PLUGS is None:
        _PLUGS = _load()
    return {k: p for k, p in _PLUGS.items() if kind is None or p.kind == kind}


def find(bus: str) -> Plug:
    """The plug of ``bus``, or a one-line ``MockError`` naming the known ones."""
    found = plugs().get(bus)
    if found is None:
        raise MockError(f"no emulator for bus {bus!r}; one of {', '.join(plugs())}")
    return found


def demo_buses() -> dict[str, Plug]:
    """The plugs ``station demo`` offers (those with a demo world), in the order ``station demo`` lists them."""
    return {k: p for k, p in plugs("robot").items() if p.demo is not None}


def cls(path: str) -> Any:
    """``"module:attribute"`` imported (a plug names its emulator class this way: nothing heavy at registry
    time)."""
    module, _, attr = path.partition(":")
    return getattr(importlib.import_module(module), attr)
