"""Dynamixel Protocol 2.0 driver (ROBOTIS X-series servos) fulfilling ``station.robot.Robot``."""

from station.drivers.dynamixel.robot import DynamixelRobot

__all__ = ["DynamixelRobot"]
