"""Open a robot by URL, python-can style: the URL's scheme names a driver class registered as an entry point.

``dynamixel:///dev/ttyUSB0?baud=1000000&ids=11-14&model=omx``
``canopen+socketcand://127.0.0.1:29536?channel=can0&nodes=1-6&model=arm6``
``canopen+virtual://chan0?nodes=1-6&model=arm6``
``ur://192.168.0.10?model=ur5e``

Drivers register in the ``station.robots`` entry-point group (``scheme = "module:Class"``, the station's own
in pyproject.toml), so a new bus is a new package, not an edit here. The class has
``from_url(url: RobotURL, **overrides) -> Robot``. Entry points are read on the first ``open_robot`` and
driver modules imported only when their scheme is opened: no bus library is imported by ``station.robot``."""

from __future__ import annotations

from station.plugins import Registry, library
from station.robot.errors import ConfigError
from station.robot.url import RobotURL, parse_url

GROUP = "station.robots"
REGISTRY = Registry(GROUP, "driver", ConfigError,
                    empty=f"no robot drivers are registered (entry-point group {GROUP} is empty): the station "
                          "package is not installed properly; reinstall it (make venv)")


def schemes() -> list[str]:
    """Every registered URL scheme."""
    return REGISTRY.names()


def bus_library(package: str):
    """Wrap a driver's import of its bus library: a missing one becomes a one-line ``ConfigError`` naming
    the package to install (python-can wraps its interfaces' import errors the same way)::

        with bus_library("ur-rtde"):
            import rtde_control
    """
    return library(package, ConfigError)


def driver_class(scheme: str) -> type:
    """The driver class registered for ``scheme`` (its module imported now)."""
    return REGISTRY.load(scheme)


def open_robot(url: str, **overrides):
    """Return a connected ``Robot`` for ``url``; ``overrides`` go to the driver's constructor."""
    parsed: RobotURL = parse_url(url)
    try:
        cls = driver_class(parsed.scheme)
    except ConfigError as e:
        raise ConfigError(f"robot URL {url!r}: {e}") from None
    return cls.from_url(parsed, **overrides)
