"""CANopen CiA 402 robots on every CAN adapter python-can speaks: ``canopen+<interface>://<channel>?...``
(socketcan, pcan, kvaser, ixxat, slcan, virtual) and ``canopen+socketcand://HOST:PORT?channel=can0&...``."""

from station.drivers.canopen.robot import CanopenRobot

__all__ = ["CanopenRobot"]
