"""What to do after a FAIL whose fit residual is above its limit: the robot has errors the procedure's parameter
group does not model. The same samples are solved again with the tool and/or the link geometry added (in
process, the solver's own API, a few tens of milliseconds each); the first group that brings the fit and the
held-out residual inside their limits is named, with the command that identifies it on the robot."""

from __future__ import annotations

import shlex

# tried in this order: the cheapest explanation first (a tool error needs one socket, link geometry three)
EXTRA_GROUPS = ("tcp", "dh", "dh,tcp")
DH_PROCEDURE, DH_MIN_SOCKETS = "dh_full", 3


def _limit_m(record: dict, name: str) -> float | None:
    for m in (record.get("verdict") or {}).get("measurements") or []:
        if m.get("name") == name and m.get("high") is not None:
            return float(m["high"]) * {"mm": 1e-3, "um": 1e-6, "m": 1.0}.get(str(m.get("unit")), 1e-3)
    return None


def _failed(record: dict, name: str) -> bool:
    return any(m.get("name") == name and m.get("passed") is False
               for m in (record.get("verdict") or {}).get("measurements") or [])


def _observations(record: dict, which: str):
    import numpy as np

    from station.solver import Observations

    rows = [s for s in record.get("samples") or [] if s.get("set", "fit") == which and s.get("q") is not None]
    if not rows:
        return None
    return Observations(np.array([s["q"] for s in rows], float), np.array([s["point"] for s in rows], dtype=object),
                        None)


def _merge(base: str, extra: str) -> str:
    names = [g for g in base.split(",") if g]
    return ",".join(names + [g for g in extra.split(",") if g not in names])


def suggest(out, *, robot: str, serial: str, cell: str | None, identify: str | None) -> list[str]:
    """Lines to print after a FAIL (empty when the fit was inside its limit, or nothing explains it)."""
    record = out.record or {}
    result, model = record.get("result"), getattr(out, "model", None)
    if not result or model is None or not _failed(record, "fit_rms"):
        return []
    fit_limit, hold_limit = _limit_m(record, "fit_rms"), _limit_m(record, "holdout_rms")
    base = identify or (result.get("settings") or {}).get("identify") or "offsets"
    rms = (result.get("residuals") or {}).get("rms_after_m")
    fit, hold = _observations(record, "fit"), _observations(record, "holdout")
    if fit is None or rms is None or fit_limit is None:
        return []
    from station.solver import solve

    head = (f"station: the fit residual {rms * 1e3:.3f} mm is above its limit {fit_limit * 1e3:.3g} mm: the robot "
            f"has errors that --identify {base} does not model")
    tried = []
    for extra in EXTRA_GROUPS:
        group = _merge(base, extra)
        if group == base or group in tried:
            continue
        tried.append(group)
        try:
            model.select(group)
            res = solve(model, fit, identify=group, reference="unknown", holdout=hold)
        except Exception:  # a group this model or these samples cannot take: try the next one
            continue
        after = res.residuals.get("rms_after_m")
        held = (res.holdout or {}).get("rms_m")
        if not res.trusted or after is None or after > fit_limit or (hold_limit and held and held > hold_limit):
            continue
        found = (f"station: on the same samples --identify {group} fits {after * 1e3:.3f} mm"
                 + (f" (held-out {held * 1e3:.3f} mm)" if held is not None else ""))
        return [head, found, "station: next: " + _command(out, group, robot, serial, cell)]
    return [head, f"station: on the same samples none of --identify {', '.join(tried)} fits inside the limit "
                  "either: check the cell (a loose socket, a wrong tool) and the robot's model"]


def _command(out, group: str, robot: str, serial: str, cell: str | None) -> str:
    """The ``station run`` line that identifies ``group`` on this robot: ``dh_full`` for link geometry (it
    needs three sockets: say so when the cell has fewer), else the same procedure with ``--identify``."""
    record = out.record or {}
    procedure = record.get("procedure") or "zero_offsets"
    sockets = {s.get("point") for s in record.get("samples") or []}
    tail = [*(["--cell", cell] if cell else [])]
    if "dh" in group.split(","):
        line = shlex.join(["station", "run", DH_PROCEDURE, "--robot", robot, "--serial", serial, *tail,
                           *(["--identify", group] if group != "offsets,dh,tcp" else [])])
        if len(sockets) < DH_MIN_SOCKETS:
            line += (f"  (link geometry needs {DH_MIN_SOCKETS} sockets spread over the workspace; this session "
                     f"touched {len(sockets)}: add sockets to the cell)")
        return line
    return shlex.join(["station", "run", procedure, "--robot", robot, "--serial", serial, *tail, "--identify",
                       group])
