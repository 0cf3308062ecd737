"""``station mock tracker --world W --canopen`` as a real process for the correction_map tests: the world's CiA 402
drives behind a socketcand hub and the laser tracker in one process, with their URLs; killed like a crash."""

from clirunner import station_spawn

# a slower SYNC and a longer heartbeat consumer time (driver URL options): the CI machine is shared; no contact
# input (the map cell measures with the tracker): subscribed, the emulator works out the world's true, gravity-
# deflected tip for that input's TPDO every 10 ms (~3/4 of the emulator's CPU with a compliant arm)
ROBOT_OPTIONS = "&sync_ms=20&heartbeat_timeout_ms=5000&sdo_timeout_ms=2000&master_timeout_ms=5000&contact=none"


class TrackerProcess:
    def __init__(self, world, can_port: int = 0, seed: int = 0) -> None:
        self.proc = station_spawn("mock", "tracker", "--world", world, "--canopen", "--can-port", can_port, "--seed",
                                  seed, module=True)
        self.tracker = self.proc.readline().split()[3]
        self.robot = self.proc.readline().split()[5] + ROBOT_OPTIONS

    def kill(self) -> None:
        """SIGKILL: a crash, no teardown of its sockets (safe to call twice)."""
        self.proc.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.kill()
