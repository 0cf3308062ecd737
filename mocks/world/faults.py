"""Fault injection shared by every emulator: a test arms a fault, the emulator consumes it once.

Emulators call ``faults.take(kind, device)`` at the point where the fault would bite (before answering
a request, before sending a frame) and act it out on the wire: no answer (``timeout``), a damaged frame
(``corrupt``), a device error status / EMCY (``device_fault``), a closed port or socket (``disconnect``),
a protective stop (``protective_stop``)."""

from __future__ import annotations

import threading
from collections.abc import Hashable
from dataclasses import dataclass

KINDS = ("timeout", "corrupt", "device_fault", "disconnect", "protective_stop")
# wire events emulators report through ``Faults.notice`` (a world file's ``at:`` trigger), with their keys
TRIGGERS = {
    "packet": {"addr", "inst"},  # Dynamixel: a write / reg write / sync write starting at control-table addr
    "sdo": {"node", "index", "sub", "op"},  # CANopen: an SDO request (op: write | read) a drive receives
    "pdo": {"node", "cob_id", "num"},  # CANopen: an RPDO a drive receives
    "rtde": {"command"},  # UR: a control-script command (movej, movel, stopj, teach_mode, ...) the controller runs
    "dashboard": {"command"},  # UR: a dashboard line (lower case: "stop", "power off", ...)
    "script": {"program"},  # UR: a program arriving on the script port (rtde_control)
}


def _matches_event(trigger: dict, event: dict) -> bool:
    for key, want in trigger.items():
        got = event.get(key)
        if isinstance(want, dict):
            if not isinstance(got, dict) or not _matches_event(want, got):
                return False
        elif got != want:
            return False
    return True


@dataclass
class PendingFault:
    kind: str
    device: Hashable | None  # None: the first device that asks
    count: int  # how many more times it fires
    after: int  # opportunities to let pass before it fires
    code: int | None = None  # optional device-specific error code for device_fault
    trigger: dict | None = None  # armed only once an emulator reports a matching wire event (``notice``)


class Faults:
    """Thread-safe queue of armed faults."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._pending: list[PendingFault] = []
        self.fired: list[tuple[str, Hashable | None]] = []  # (kind, device) in the order consumed

    def inject(self, kind: str, device: Hashable | None = None, count: int = 1, *, after: int = 0,
               code: int | None = None, trigger: dict | None = None) -> None:
        """Arm ``count`` faults of ``kind`` for ``device`` (None: any device), firing after ``after``
        opportunities have passed; with ``trigger`` (e.g. ``{"packet": {"addr": 20}}``) only once an emulator
        has reported a matching wire event through :meth:`notice` (the phase a write-back is in, ...)."""
        if kind not in KINDS:
            raise ValueError(f"unknown fault kind {kind!r}; known: {', '.join(KINDS)}")
        if count < 1 or after < 0:
            raise ValueError(f"fault {kind!r}: count must be >= 1 and after >= 0 (got {count}, {after})")
        with self._lock:
            self._pending.append(PendingFault(kind, device, int(count), int(after), code, trigger))

    def notice(self, **event) -> None:
        """An emulator saw a wire event, e.g. ``notice(packet={"addr": 20})`` for a Dynamixel write to
        address 20: faults waiting for it are armed from now on (their trigger's keys all match)."""
        with self._lock:
            for f in self._pending:
                if f.trigger is not None and _matches_event(f.trigger, event):
                    f.trigger = None

    def waiting(self) -> bool:
        """True while some fault waits for a wire event (emulators skip building events otherwise)."""
        with self._lock:
            return any(f.trigger is not None for f in self._pending)

    @staticmethod
    def _matches(f: PendingFault, kind: str, device: Hashable | None) -> bool:
        if f.kind != kind or f.trigger is not None:
            return False
        return f.device is None or device is None or f.device == device or str(f.device) == str(device)

    def take(self, kind: str, device: Hashable | None = None) -> bool:
        """Consume one armed fault of ``kind`` matching ``device``; True if the caller must act it out."""
        return self.take_fault(kind, device) is not None

    def take_fault(self, kind: str, device: Hashable | None = None) -> PendingFault | None:
        """Like :meth:`take` but returns the fault (with its ``code``) or None."""
        with self._lock:
            for f in self._pending:
                if not self._matches(f, kind, device):
                    continue
                if f.after > 0:
                    f.after -= 1
                    return None
                f.count -= 1
                if f.count <= 0:
                    self._pending.remove(f)
                self.fired.append((kind, device))
                return PendingFault(kind, device if device is not None else f.device, 1, 0, f.code)
        return None

    def peek(self, kind: str, device: Hashable | None = None) -> bool:
        """True if a fault of ``kind`` for ``device`` is armed (does not consume it)."""
        with self._lock:
            return any(self._matches(f, kind, device) for f in self._pending)

    def pending(self) -> list[PendingFault]:
        with self._lock:
            return [PendingFault(f.kind, f.device, f.count, f.after, f.code, f.trigger) for f in self._pending]

    def clear(self) -> None:
        with self._lock:
            self._pending.clear()
