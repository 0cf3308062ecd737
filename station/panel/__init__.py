"""The operator panel (``station panel``): a local web page and JSON API over the same engine, journal,
resume and records as ``station run`` (docs/panel.md)."""

from station.panel.controller import Controller, PanelConfig, PanelError

__all__ = ["Controller", "PanelConfig", "PanelError"]
