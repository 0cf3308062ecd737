"""Option values with their unit: the command line's name for :mod:`station.quantity` (the one reading, shared
with the options procedures declare)."""

from station.quantity import parse_option, parse_xyz

__all__ = ["parse_option", "parse_xyz"]
