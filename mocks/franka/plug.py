"""The Franka emulator as the station's tools see it (``station.emulators`` entry point ``franka``): always
``station mock franka`` in a child process (franka-sim runs in its own environment, ``make franka-sim``), on a
free random loopback address 127.x.y.z (libfranka's port 1337 is fixed: one robot per address)."""

from __future__ import annotations

from station.mocks.plug import CHILD, Demo, Plug


class FrankaPlug(Plug):
    bus = "franka"
    cli = "station.mocks.franka.cli"
    modes = (CHILD,)
    default_model = "fr3"
    # a ball 60 mm off the flange axis (joint 7's zero shows through its lever), seated by the arm's impedance
    # in the world's two sockets, whose surveyed positions are the reference; at 1.5 rad/s. Zero errors of a
    # few hundredths of a degree (a Franka's), so the ball starts within the sockets' capture
    demo = Demo(model="fr3", options={"reference": "cell", "cone_deg": 35.0}, query="&speed=1.5",
                world={"robot": {"tool": {"x": 0.06, "y": 0.0, "z": 0.15, "rx": 0.0, "ry": 0.0, "rz": 0.0}}},
                sigma_deg=0.03)

    def child_args(self, emu) -> list[str]:
        from station.mocks.franka.simenv import free_loopback

        emu.host = emu.host or free_loopback()
        return ["--host", emu.host, *(["--serial", emu.serial] if emu.serial else [])]

    def serial_in_url(self, emu) -> bool:
        return False  # `station mock franka --serial` prints it in the URL (the FCI reports none)

    def power_cycle_child(self, emu) -> None:
        """The robot off and on: the simulator process ends and starts again on the same address with the same
        world (what the robot keeps, its served model, is in the world; its errors, impedance settings and
        motions are gone). franka-sim has no brakes: the arm comes back at the world's start pose."""
        from station.mocks.launch import end_child

        proc, emu.proc = emu.proc, None
        end_child(proc, timeout=15.0)
        emu._start_child()


PLUG = FrankaPlug()
