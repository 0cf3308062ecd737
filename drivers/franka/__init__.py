"""Franka Research 3 over the FCI through pylibfranka: ``franka://HOST[?model=fr3&serial=SN]``."""

from station.drivers.franka.robot import FrankaRobot

__all__ = ["FrankaRobot"]
