"""The technician's jog terminal UI (``station jog``): a textual app over a widget-free controller, on an engine
session in technician mode (``station.tui.session``)."""

from station.tui.controller import JogController, parse_reference

__all__ = ["JogController", "parse_reference"]
