"""The technician's jog terminal UI (``station jog``): a textual app over a widget-free controller."""

from station.tui.controller import JogController, parse_reference
from station.tui.session import JogSession

__all__ = ["JogController", "JogSession", "parse_reference"]
