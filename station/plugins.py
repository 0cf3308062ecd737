"""Plugs: what the station's robot drivers (``station.robots``), measuring instruments (``station.instruments``) and
emulators (``station.emulators``) share, written once (python-can's interface registry and ``BusABC``).

- :class:`Registry`: one entry-point group, read on first use (``importlib.metadata`` costs ~50 ms: only when a
  plug is opened), a plug's module imported only when it is asked for, an unknown name and a plug whose library is
  missing each a one-line error of the caller's type;
- :func:`library`: a plug's import of its third-party library, a missing one a one-line error naming the package
  to install (python-can wraps its interfaces' import errors the same way);
- :class:`CloseOnce`: the close-once lifecycle (``close()`` runs ``_shutdown()`` exactly once, also on a plug whose
  constructor failed half way; ``with plug:``; ``closed``; use after close refused).

It imports nothing of the station, so both sides of the wire (``station.robot``, ``station.instruments`` and
``station.mocks``) can use it; each passes its own error type."""

from __future__ import annotations

import contextlib
from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Any, ClassVar

if TYPE_CHECKING:
    from collections.abc import Iterator
    from importlib.metadata import EntryPoint


def missing_library(e: ModuleNotFoundError) -> bool:
    """Whether a failed import is of a module outside the station (a missing station module is a bug: the caller
    keeps its traceback)."""
    return (e.name or "").split(".")[0] != "station"


@contextlib.contextmanager
def library(package: str, error: type[Exception]) -> Iterator[None]:
    """Wrap a plug's import of its library: a missing one raises ``error`` naming the package to install."""
    try:
        yield
    except ModuleNotFoundError as e:
        if not missing_library(e):
            raise
        raise error(f"the Python package {package} is not installed (import of {e.name!r} failed); "
                    f"install it: pip install {package}") from None


class Registry:
    """The plugs of one entry-point group (``name = "module:attribute"``) by name.

    ``kind`` names a plug in messages ("driver", "instrument", "emulator"), ``noun`` what a name is ("scheme"),
    ``error`` the exception the caller's users get, ``empty`` the message when the group has no entry at all
    (None: the ordinary unknown-name message), ``fold_case`` whether names compare case-blind (URL schemes)."""

    def __init__(self, group: str, kind: str, error: type[Exception], *, noun: str = "scheme",
                 empty: str | None = None, fold_case: bool = True) -> None:
        self.group, self.kind, self.error, self.noun = group, kind, error, noun
        self.empty, self.fold_case = empty, fold_case
        self._entries: dict[str, EntryPoint] | None = None

    def _key(self, name: str) -> str:
        return name.lower() if self.fold_case else name

    def entries(self) -> dict[str, EntryPoint]:
        """Every entry point of the group by name, read once."""
        if self._entries is None:
            from importlib import metadata

            self._entries = {self._key(ep.name): ep for ep in metadata.entry_points(group=self.group)}
        return self._entries

    def names(self) -> list[str]:
        """Every registered name, sorted."""
        return sorted(self.entries())

    def entry(self, name: str) -> EntryPoint:
        """The entry point of ``name``; ``error`` naming the known ones otherwise."""
        ep = self.entries().get(self._key(name))
        if ep is None:
            known = self.names()
            if not known and self.empty:
                raise self.error(self.empty)
            raise self.error(f"unknown {self.noun} {name!r}; known: {', '.join(known) or 'none'}")
        return ep

    def load(self, name: str) -> Any:
        """What ``name``'s entry point names, its module imported now. A library the plug needs and did not wrap
        in :func:`library` is a one-line ``error``."""
        ep = self.entry(name)
        try:
            return ep.load()
        except ModuleNotFoundError as e:
            if not missing_library(e):
                raise
            raise self.error(f"the {name} {self.kind} ({ep.value}) needs the Python module {e.name!r}, which is not "
                             "installed") from None


class CloseOnce(ABC):
    """The lifecycle every plug shares: ``close()`` runs the subclass's ``_shutdown()`` exactly once (class-level
    defaults keep it valid before the constructor ran), ``with plug:`` closes it, ``closed`` says so, and
    ``_check_open(what)`` refuses use after close with ``closed_error`` naming the plug (``noun``)."""

    noun: ClassVar[str] = "plug"  # what to open again, in the refusal: "robot", "instrument"
    closed_error: ClassVar[type[Exception]] = RuntimeError
    url: str = ""
    _closed: bool = False  # class default: close() of a half-built plug

    @abstractmethod
    def _shutdown(self) -> None:
        """Release what the plug holds. Runs once, possibly on a half-constructed plug; must not raise for a link
        that is already gone."""

    def close(self) -> None:
        """Release the plug. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._shutdown()

    @property
    def closed(self) -> bool:
        return self._closed

    def _check_open(self, what: str) -> None:
        if self._closed:
            raise self.closed_error(f"{what}: {self.url or type(self).__name__} is closed; open the {self.noun} again")

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.url or '?'}{' closed' if self._closed else ''}>"
