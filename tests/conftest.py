"""Shared fixtures. Kept small and generic; ask the records/report owner before adding here.

``session_factory``: a realistic session record dict (docs/architecture.md) built from a simulated UR5e with
hidden zero-offset errors touching one fixed point, fitted here by a small Gauss-Newton so that records and
report tests do not depend on the engine or the solver. The hidden truth is returned alongside."""

from __future__ import annotations

import math
import os
import shutil
import socket
import subprocess
import tempfile
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest

from station.kinematics import load_model

HIDDEN = {"offset.j2": 0.0021, "offset.j3": -0.0017, "offset.j4": 0.0012, "offset.j5": -0.0009}
POINT_A = np.array([0.45, 0.15, 0.10])


def _touch_q(truth, point, n, rng):
    lo, hi = truth.lower, truth.upper
    centre = np.array([0.3, -1.2, 1.5, -1.9, -1.57, 0.0])
    out = []
    while len(out) < n:
        seeds = np.clip(centre + rng.uniform(-0.7, 0.7, size=(2 * n, 6)), lo, hi)
        res = truth.ik(np.broadcast_to(point, (len(seeds), 3)), seeds, tol_pos=1e-10, max_iter=300)
        out.extend(res.q[res.ok & (res.position_error < 1e-9)])
    return np.array(out[:n])


def _fit(nominal, q, names):
    """Offsets + unknown point A by Gauss-Newton; unidentifiable columns found by projection."""
    idx = [nominal.index(n) for n in names]
    x = nominal.params.copy()
    a = nominal.position(q).mean(axis=0)

    def res_jac(x, a):
        r = (nominal.position(q, x) - a).reshape(-1)
        jp = nominal.jacobian_params(q, x)[:, :3, idx].reshape(-1, len(idx))
        ja = -np.tile(np.eye(3), (len(q), 1))
        return r, np.hstack([jp, ja])

    def gauss_newton(x, a, cols):
        for _ in range(8):
            r, J = res_jac(x, a)
            full = np.zeros(J.shape[1])
            full[cols] = np.linalg.lstsq(J[:, cols], -r, rcond=1e-8)[0]
            x = x.copy()
            x[idx] += full[: len(idx)]
            a = a + full[len(idx):]
        return x, a

    r0, J = res_jac(x, a)
    # decide identifiability at a preliminary solution, where the tips gather within noise of the point
    x1, a1 = gauss_newton(x, a, list(range(J.shape[1])))
    _, J1 = res_jac(x1, a1)
    cols, reasons = [], {}
    # point columns first: an offset that only rotates the point about an axis is the one to drop
    n_par = len(idx)
    for j in [*range(n_par, n_par + 3), *range(n_par)]:
        c = J1[:, j]
        if np.linalg.norm(c) < 1e-9:
            reasons[j] = "does not move the tool point in these poses"
            continue
        if cols:
            A = J1[:, cols]
            rest = c - A @ np.linalg.lstsq(A, c, rcond=None)[0]
            if np.linalg.norm(rest) < 1e-3 * np.linalg.norm(c):  # ~ noise / reach
                reasons[j] = "not separable from the unknown reference point position"
                continue
        cols.append(j)
    cols.sort()
    x, a = gauss_newton(x, a, cols)
    r, J = res_jac(x, a)
    dof = r.size - len(cols)
    sigma = math.sqrt(float(r @ r) / dof)
    cov = np.linalg.inv(J[:, cols].T @ J[:, cols]) * sigma**2
    std = dict(zip(cols, np.sqrt(np.diag(cov)), strict=True))
    return x, a, r0.reshape(-1, 3), r.reshape(-1, 3), std, reasons, sigma


def make_session(seed: int = 0, n: int = 16, n_holdout: int = 4, noise: float = 20e-6, serial: str = "UR5E-20231",
                 session_id: str | None = None, started: datetime | None = None, limit_mm: float = 0.1,
                 writeback: bool = True) -> tuple[dict, dict]:
    """(session record dict, hidden truth {name: SI}) for a zero-offset tip-touch session."""
    rng = np.random.default_rng(seed)
    nominal = load_model("ur5e")
    truth = nominal.with_params(HIDDEN)
    q = _touch_q(truth, POINT_A, n + n_holdout, rng)
    # touch noise at the tip, mapped into the joint readings
    _, Jq, _ = truth.jacobians(q)
    q = q + np.einsum("nij,nj->ni", np.linalg.pinv(Jq[:, :3]), rng.normal(0, noise, size=(len(q), 3)))
    names = [f"offset.j{i}" for i in range(1, 7)]
    x, a, rb, ra, std, reasons, sigma = _fit(nominal, q[:n], names)
    params = {}
    for j, name in enumerate(names):
        ok = j in std
        params[name] = {"value": float(x[nominal.index(name)]) if ok else 0.0, "std": float(std[j]) if ok else None,
                        "identifiable": ok, "reason": None if ok else reasons[j], "nominal": 0.0, "kind": "model",
                        "unit": "rad"}
    for k, axis in enumerate("xyz"):
        j = len(names) + k
        params[f"point.A.{axis}"] = {"value": float(a[k]), "std": float(std[j]), "identifiable": True,
                                     "reason": None, "nominal": math.nan, "kind": "point", "unit": "m"}
    db, da = np.linalg.norm(rb, axis=1), np.linalg.norm(ra, axis=1)
    ho = np.linalg.norm(nominal.position(q[n:], x) - a, axis=1)
    ho0 = np.linalg.norm(nominal.position(q[n:]) - a, axis=1)
    result = {
        "format": "station-calibration/1", "units": "SI (m, rad)", "model": "ur5e", "parameters": params,
        "identified": [k for k, v in params.items() if v["identifiable"]],
        "unidentifiable": {k: v["reason"] for k, v in params.items() if not v["identifiable"]},
        "residuals": {"rms_before_m": float(np.sqrt(np.mean(db**2))), "max_before_m": float(db.max()),
                      "rms_after_m": float(np.sqrt(np.mean(da**2))), "max_after_m": float(da.max()),
                      "per_sample_before_m": db.tolist(), "per_sample_after_m": da.tolist()},
        "rank": len(std), "n_parameters": len(params), "condition_number": None, "observability_index": None,
        "sigma_m": sigma, "converged": True, "iterations": 8, "n_samples": n, "n_residuals": 3 * n,
        "holdout": {"n_samples": n_holdout, "rms_m": float(np.sqrt(np.mean(ho**2))), "max_m": float(ho.max()),
                    "rms_nominal_m": float(np.sqrt(np.mean(ho0**2)))} if n_holdout else None,
        "covariance": None, "settings": {"identify": "offsets", "reference": "unknown"}, "notes": []}
    sid = session_id or f"20261121-{seed:04d}-{serial}"
    t0 = started or datetime(2026, 11, 21, 8, 0, tzinfo=UTC) + timedelta(minutes=seed)
    samples = []
    for i, qi in enumerate(q):
        raw = [int(round(v * 1e6)) for v in qi]
        samples.append({"type": "sample", "seq": 10 + 2 * i, "session": sid, "point": "A", "q": qi.tolist(),
                        "raw": raw, "raw_unit": "rad", "t": t0.timestamp() + 5.0 * i, "t_device": 100.0 + 5.0 * i,
                        "measured": None, "pose": i, "set": "fit" if i < n else "holdout",
                        "status": {"enabled": True, "faults": []}})
    rms_mm = result["residuals"]["rms_after_m"] * 1e3
    ho_mm = result["holdout"]["max_m"] * 1e3 if n_holdout else rms_mm
    meas = [
        {"name": "rms_after", "value": rms_mm, "unit": "mm", "low": None, "high": limit_mm,
         "marginal": 0.2 * limit_mm, "passed": rms_mm <= limit_mm},
        {"name": "holdout_max", "value": ho_mm, "unit": "mm", "low": None, "high": 2 * limit_mm,
         "marginal": 0.4 * limit_mm, "passed": ho_mm <= 2 * limit_mm},
        {"name": "offset.j2", "value": math.degrees(params["offset.j2"]["value"]), "unit": "deg", "low": -1.0,
         "high": 1.0, "marginal": 0.1, "passed": abs(math.degrees(params["offset.j2"]["value"])) <= 1.0},
    ]
    before = {f"offset.j{i}": 0.01 * i for i in range(1, 7)}
    after = {k: v + (params[k]["value"] if params[k]["identifiable"] else 0.0) for k, v in before.items()}
    session = {
        "session": sid, "serial": serial, "procedure": "zero_offsets", "procedure_sha256": "ab" * 32,
        "station": "eol-station-3", "operator": "j.doe", "started": t0.isoformat(),
        "finished": (t0 + timedelta(seconds=5 * len(q) + 20)).isoformat(),
        "robot": {"vendor": "Universal Robots", "model": "ur5e", "serial": serial, "firmware": "5.15.0",
                  "devices": [], "url": "ur://127.0.0.1:30004"},
        "model": "ur5e", "samples": samples, "result": result,
        "verdict": {"passed": all(m["passed"] for m in meas), "measurements": meas},
        "writeback": {"before": before, "after": after, "applied": True, "verified": True} if writeback else None,
    }
    return session, dict(HIDDEN)


@pytest.fixture
def emulators():
    """Factory ``emulators(bus, world, **kw) -> Emulator`` (``station.mocks.launch``, started): ``.url`` is what
    the station opens; ``world`` a world file or, in-process, a ``World``. Every one is closed at teardown."""
    from station.mocks.launch import launch

    started = []

    def start(bus: str, world=None, **kw):
        emu = launch(bus, world, **kw)
        started.append(emu)
        return emu.start()

    yield start
    for emu in reversed(started):
        emu.close()


@pytest.fixture(scope="session")
def session_factory():
    """``make_session(seed=..., ...) -> (session dict, hidden truth)``; see ``make_session``."""
    return make_session


# ---- PostgreSQL: a real server ---------------------------------------------------------------------------
@pytest.fixture(scope="session")
def pg_url():
    """SQLAlchemy URL of a real PostgreSQL: ``$STATION_TEST_PG_URL``, else a throwaway cluster started with
    ``.ci/pg-start`` (needs the Debian ``postgresql`` server binaries) and stopped afterwards. Neither
    available: the test fails (CI guarantees a server; a silent skip would hide the PostgreSQL path)."""
    url = os.environ.get("STATION_TEST_PG_URL")
    if url:
        yield url
        return
    bins = sorted(Path("/usr/lib/postgresql").glob("*/bin/postgres"))
    if not bins:
        pytest.fail("PostgreSQL tests need a server: set STATION_TEST_PG_URL or install the Debian 'postgresql' "
                    "package (.ci/run does both)", pytrace=False)
    root = Path(__file__).resolve().parents[1]
    # not under pytest's 0700 tmp dir: the cluster runs as user postgres when we are root
    data = Path(tempfile.mkdtemp(prefix="station-pg-"))
    data.chmod(0o755)
    with socket.socket() as sock:  # a free loopback port (the cluster binds it a moment later)
        sock.bind(("127.0.0.1", 0))
        port = str(sock.getsockname()[1])
    env = {**os.environ, "PGDATA_DIR": str(data / "cluster"), "PGPORT_CI": port}
    out = subprocess.run(["bash", str(root / ".ci" / "pg-start")], env=env, capture_output=True, text=True,
                         timeout=120)
    if out.returncode != 0:
        pytest.fail(f".ci/pg-start failed: {out.stderr.strip() or out.stdout.strip()}", pytrace=False)
    try:
        yield out.stdout.strip().splitlines()[-1]
    finally:
        pg_ctl = bins[-1].parent / "pg_ctl"
        cmd = [str(pg_ctl), "-D", str(data / "cluster"), "-m", "immediate", "-w", "stop"]
        if os.geteuid() == 0:
            cmd = ["runuser", "-u", "postgres", "--", *cmd]
        subprocess.run(cmd, capture_output=True, timeout=60)
        shutil.rmtree(data, ignore_errors=True)


@pytest.fixture
def tui_no_idle_wait(monkeypatch):
    """For textual pilot tests next to bus threads: the pilot waits after each key until the process *looks*
    idle (CPU time vs wall clock), at most 1 s, and the bus/emulator threads never let it look idle, so every
    key cost 2 s. Key handling stays deterministic without it: ``press`` still waits until the screen has
    processed every queued message. Use with ``pytestmark = pytest.mark.usefixtures("tui_no_idle_wait")``."""
    import asyncio

    async def yield_once(min_sleep: float = 0.0, max_sleep: float = 0.0) -> None:
        await asyncio.sleep(0)

    monkeypatch.setattr("textual.app.wait_for_idle", yield_once)
    monkeypatch.setattr("textual.pilot.wait_for_idle", yield_once)


@pytest.fixture
def robot_rig():
    """Factory ``robot_rig(bus, world, *, query="", enable=True, connect=True, **emulator_options) -> (emulator,
    robot)``: the emulated devices of ``bus`` serving the ``World`` in this process (CANopen drives on a python-can
    virtual channel of their own, Dynamixel servos on a pty) and the real driver connected to them through its URL
    (``open_robot``; ``query`` is appended, e.g. ``"&heartbeat_ms=250"``), enabled. ``connect=False``: the
    emulator alone (robot None), for a test that talks to the devices below the driver first (the vendor's SDK, a
    raw CANopen node) or opens the robot itself (``emulator.url``). Robots are closed before their emulators at
    teardown. A world file, a UR controller or a child process: the ``emulators`` fixture."""
    from station.robot import open_robot

    made: list = []

    def make(bus: str, world, *, query: str = "", enable: bool = True, connect: bool = True, **options):
        if bus == "canopen":
            import uuid

            from station.mocks.canopen.emulator import CanopenEmulator

            channel = f"rig{uuid.uuid4().hex[:10]}"
            emu = CanopenEmulator(world, "virtual", channel, **options).start()
            made.append(emu)
            nodes = ",".join(str(n) for n in emu.nodes)
            url = f"canopen+virtual://{channel}?nodes={nodes}&model={world.nominal.name}"
        elif bus == "dynamixel":
            from station.mocks.dynamixel import DynamixelEmulator

            emu = DynamixelEmulator(world, **options).start()
            made.append(emu)
            url = emu.url
        else:
            raise ValueError(f"robot_rig: no in-process emulator for bus {bus!r} (use the emulators fixture)")
        if not connect:
            return emu, None
        robot = open_robot(url + query)
        made.append(robot)
        if enable:
            robot.enable()
        return emu, robot

    yield make
    for thing in reversed(made):
        thing.close() if hasattr(thing, "close") else thing.stop()
