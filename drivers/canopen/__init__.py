"""CANopen CiA 402 robots: ``canopen+virtual://CHANNEL?...`` and ``canopen+socketcand://HOST:PORT?...``."""

from station.drivers.canopen.robot import CanopenRobot

__all__ = ["CanopenRobot"]
