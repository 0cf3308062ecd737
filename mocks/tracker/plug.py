"""The laser-tracker emulator as the station's tools see it (``station.emulators`` entry point ``tracker``): an
instrument (its URL opens with ``station.instruments.open_instrument``), launched in the caller's process next
to the robot's emulator, since it measures the world that robot moves; placed and identified by the world's
``buses.tracker`` section. ``station mock tracker`` is its command."""

from __future__ import annotations

from station.mocks.plug import Plug


class TrackerPlug(Plug):
    bus = "tracker"
    cli = "station.mocks.tracker.cli"
    kind = "instrument"
    default_model = "hexapod"

    def build(self, world):
        from station.mocks.tracker.config import tracker_config
        from station.mocks.tracker.server import TrackerServer

        return TrackerServer(world, tracker_config(world.bus_config("tracker")), seed=world.spec.seed)

    def serial_in_url(self, emu) -> bool:
        return False  # the instrument reports its serial number (ID)


PLUG = TrackerPlug()
