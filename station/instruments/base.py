"""``InstrumentBase``: what every measuring instrument driver shares, as ``RobotBase`` is for robots (python-can's
``BusABC`` idea; the lifecycle is ``station.plugins.CloseOnce``, the robots' too): ``close()`` runs ``_shutdown()``
exactly once (also on an instrument whose constructor failed half way), ``with instrument:`` closes it, ``closed``
says so, a reading from a closed instrument is refused;
the class declares its URL ``options`` (``station.robot.url.Options``) and ``url_example``, and
``from_url`` parses them."""

from __future__ import annotations

from abc import abstractmethod
from typing import ClassVar

from station.instruments.protocol import InstrumentIdentity, PoseReading
from station.plugins import CloseOnce
from station.robot.errors import ConnectionLost
from station.robot.url import Options, RobotURL, parse_url


class InstrumentBase(CloseOnce):
    options: ClassVar[Options] = Options()  # the URL query options this instrument accepts
    url_example: ClassVar[str] = "SCHEME://HOST"  # how its URL looks, for messages ("--tracker tcp://HOST:PORT")
    noun: ClassVar[str] = "instrument"
    closed_error: ClassVar[type[Exception]] = ConnectionLost

    @classmethod
    def parse(cls, url: str | RobotURL) -> tuple[RobotURL, dict]:
        """The URL and its option values (declared defaults filled in); one-line ``ConfigError`` otherwise."""
        u = url if isinstance(url, RobotURL) else parse_url(str(url))
        return u, cls.options.parse(u, what="instrument URL")

    @classmethod
    @abstractmethod
    def from_url(cls, url: str | RobotURL, **overrides) -> InstrumentBase:
        """A connected, identified instrument for ``url``; ``overrides`` replace constructor arguments."""

    @abstractmethod
    def identity(self) -> InstrumentIdentity:
        """Who this instrument is (serial, model, what it states about its noise)."""

    @abstractmethod
    def measure(self) -> PoseReading:
        """One stationary reading of the probe."""
