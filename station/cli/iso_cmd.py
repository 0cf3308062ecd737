"""``station iso9283 --samples FILE --out RESULT.json``: the ISO 9283 pose characteristics of commanded and
attained poses from any instrument (docs/iso9283.md, "Offline").

CSV (units in the headers, SI when none; ``#`` lines are comments; other columns ignored): ``pose`` (label, e.g.
P1), ``cycle`` (integer), commanded ``x_c,y_c,z_c`` and attained ``x,y,z`` in the robot base frame, optionally
``rx_c,ry_c,rz_c`` and ``rx,ry,rz`` (rotation vectors) for the orientation terms, optionally ``direction`` (the
approach direction's label: the rows of ``--direction`` (default: the first row's) give AP, RP, AD and RD; every
direction of a pose gives its vAP)."""

from __future__ import annotations

from pathlib import Path

import typer

from station.lazy import lazy_module
from station.robot.errors import ConfigError

np = lazy_module("numpy")

POSITION = ("x", "y", "z")
ROTATION = ("rx", "ry", "rz")
SAME = 1e-6  # m or rad: rows of one pose must command the same pose to this


def _need(t, names: list[str]) -> None:
    for name in names:
        if name not in t.columns:
            raise ConfigError(f"{t.path}:{t.header_line}: missing column {name!r} (pose, cycle, x_c, y_c, z_c, "
                              "x, y, z; optionally rx_c..rz_c and rx..rz, direction)")


def read_iso_samples(path: Path, direction: str | None = None) -> dict:
    """The CSV as ``{"commanded": {pose: (3|6,)}, "attained": {pose: (n, 3|6)}, "cycles": {pose: [..]},
    "directions": {pose: {dir: (n, 3|6)}}, "direction": name, "rows": N}`` (SI); one line naming file, line and
    column for anything wrong."""
    from station.samplesfile import SamplesFileError, column_si, read_table

    try:
        t = read_table(path)
        _need(t, ["pose", "cycle", *(f"{a}_c" for a in POSITION), *POSITION])
        rot = [c for c in (*(f"{a}_c" for a in ROTATION), *ROTATION) if c in t.columns]
        if rot and len(rot) != 6:
            missing = [c for c in (*(f"{a}_c" for a in ROTATION), *ROTATION) if c not in t.columns]
            raise ConfigError(f"{t.path}:{t.header_line}: missing column {missing[0]!r} (orientation needs "
                              "rx_c, ry_c, rz_c and rx, ry, rz)")
        if not t.rows:
            raise ConfigError(f"{t.path}: no data rows")
        cmd = np.column_stack([column_si(t, f"{a}_c", "length") for a in POSITION]
                              + [column_si(t, f"{a}_c", "angle") for a in ROTATION if rot])
        att = np.column_stack([column_si(t, a, "length") for a in POSITION]
                              + [column_si(t, a, "angle") for a in ROTATION if rot])
    except SamplesFileError as e:
        raise ConfigError(str(e)) from None
    kp, kc = t.columns["pose"][0], t.columns["cycle"][0]
    kd = t.columns["direction"][0] if "direction" in t.columns else None
    labels, cycles, dirs = [], [], []
    for i, row in enumerate(t.rows):
        if not row[kp]:
            raise ConfigError(f"{t.where(i)}: column 'pose': empty")
        try:
            cycles.append(int(row[kc]))
        except ValueError:
            raise ConfigError(f"{t.where(i)}: column 'cycle': not an integer ({row[kc]!r})") from None
        labels.append(row[kp])
        dirs.append(row[kd] if kd is not None else "")
    uni = direction if direction is not None else dirs[0]
    if direction is not None and direction not in dirs:
        raise ConfigError(f"--direction {direction!r}: {t.path} has directions {', '.join(sorted(set(dirs)))}")
    seen: dict[tuple, int] = {}
    first: dict[str, int] = {}
    out: dict = {"commanded": {}, "attained": {}, "cycles": {}, "directions": {}, "direction": uni or None,
                 "rows": len(t.rows)}
    groups: dict[tuple[str, str], list[int]] = {}
    for i, (p, c, d) in enumerate(zip(labels, cycles, dirs, strict=True)):
        if (p, d, c) in seen:
            raise ConfigError(f"{t.where(i)}: pose {p} cycle {c}{' direction ' + d if d else ''} is also on line "
                              f"{t.lines[seen[p, d, c]]}")
        seen[p, d, c] = i
        j = first.setdefault(p, i)
        diff = np.abs(cmd[i] - cmd[j])
        if diff.max() > SAME:
            raise ConfigError(f"{t.where(i)}: pose {p}: commanded pose differs from line {t.lines[j]} by "
                              f"{diff.max():.3g} (m or rad); each pose is commanded the same in every cycle")
        groups.setdefault((p, d), []).append(i)
    for (p, d), rows in groups.items():
        rows = sorted(rows, key=lambda i: cycles[i])
        out["directions"].setdefault(p, {})[d or "-"] = att[rows]
        if d == uni:
            out["commanded"][p] = cmd[rows[0]]
            out["attained"][p] = att[rows]
            out["cycles"][p] = [cycles[i] for i in rows]
    return out


def _pair(text: str | None, data: dict, given: bool) -> tuple[str, str] | None:
    names = [s.strip() for s in (text or "").split(",") if s.strip()]
    if len(names) != 2 or names[0] == names[1]:
        raise ConfigError(f"--pair {text!r}: expected two pose labels, e.g. P2,P4")
    missing = [p for p in names if p not in data["attained"]]
    if missing:
        if given:
            raise ConfigError(f"--pair {text}: no pose {missing[0]} in the samples (poses: "
                              f"{', '.join(data['attained'])})")
        return None
    c1, c2 = (data["cycles"][p] for p in names)
    if c1 != c2:
        raise ConfigError(f"--pair {text}: the two poses need the same cycles (distance per cycle): {names[0]} has "
                          f"{len(c1)}, {names[1]} {len(c2)} (first difference near cycle "
                          f"{next((a for a, b in zip(c1, c2, strict=False) if a != b), min(len(c1), len(c2)))})")
    return names[0], names[1]


def evaluate_file(samples: Path, *, direction: str | None = None, pair: str | None = None,
                  level: float = 0.95, noise: str | None = None) -> dict:
    from station.performance.iso9283 import IsoError, evaluate

    if not 0.5 <= level < 1:
        raise ConfigError(f"--confidence {level!r}: expected a level in [0.5, 1), e.g. 0.95")
    data = read_iso_samples(samples, direction)
    sigma = None
    if noise is not None:
        from station.kinematics.tolerances import parse_quantity

        try:
            sigma, quantity = parse_quantity(noise)
        except ValueError as e:
            raise ConfigError(f"--noise {e}") from None
        if quantity != "length" or not sigma > 0:
            raise ConfigError(f"--noise {noise!r}: expected the instrument's per-axis noise as a length, e.g. 30um")
    the_pair = _pair(pair or "P2,P4", data, pair is not None)
    vap = {p: d for p, d in data["directions"].items() if len(d) >= 2}
    try:
        res = evaluate(data["commanded"], data["attained"], directions=vap or None, pair=the_pair, level=level,
                       instrument_sigma=sigma)
    except IsoError as e:
        raise ConfigError(f"{samples}: {e}") from None
    res["source"] = {"file": str(samples), "rows": data["rows"], "direction": data["direction"],
                     "cycles": {p: len(c) for p, c in data["cycles"].items()}}
    return res


def print_result(res: dict, echo=typer.echo) -> None:
    """The per-pose table a quality engineer reads (mm, deg), then the worst pose per figure."""
    def mm(v):
        return "-" if v is None else f"{v * 1e3:.4f}"

    def ci(v):
        return "" if not v else f"[{v[0] * 1e3:.4f}, {v[1] * 1e3:.4f}]"

    echo(f"ISO 9283 pose characteristics ({res['confidence']:.0%} intervals; mm)")
    echo(f"  {'pose':6s} {'n':>3s} {'AP_p':>9s} {'interval':>21s} {'RP_l':>9s} {'interval':>21s} {'vAP_p':>9s}")
    for p, d in res["poses"].items():
        echo(f"  {p:6s} {d['n']:3d} {mm(d['AP_p']):>9s} {ci(d['AP_p_ci']):>21s} {mm(d['RP_l']):>9s} "
             f"{ci(d.get('RP_l_ci')):>21s} {mm(d.get('vAP_p')):>9s}")
    dist = res.get("distance")
    if dist:
        echo(f"  distance {'-'.join(dist['poses'])}: AD_p {mm(dist['AD_p'])} {ci(dist['AD_p_ci'])}, RD_p "
             f"{mm(dist['RD_p'])} {ci(dist['RD_p_ci'])} (commanded {mm(dist['D_c'])})")
    inst = res.get("instrument")
    if inst:
        echo(f"  instrument noise {inst['sigma_m'] * 1e6:.1f} um per axis: RP_l below "
             f"{inst['rp_certifiable_above_m'] * 1e3:.4f} mm cannot be told from it")


def iso9283(
    samples: Path = typer.Option(..., "--samples", help="CSV: pose, cycle, x_c,y_c,z_c, x,y,z (base frame; units "
                                 "in headers, e.g. x[mm]); optional rx_c..rz_c, rx..rz, direction."),
    out: Path = typer.Option(None, "--out", help="Write the result JSON (station-iso9283/1, SI) here."),
    direction: str = typer.Option(None, "--direction", help="The uni-directional series (default: the first "
                                  "row's direction); every direction of a pose gives its vAP."),
    pair: str = typer.Option(None, "--pair", help="Distance accuracy between these two poses (default P2,P4)."),
    confidence: float = typer.Option(0.95, "--confidence", help="Level of the intervals."),
    noise: str = typer.Option(None, "--noise", help="The instrument's per-axis noise, e.g. 30um: the RP floor."),
) -> None:
    """ISO 9283 pose characteristics (AP, RP, vAP, AD, RD with confidence intervals) from commanded and attained
    poses."""
    from station.safeio import dumps_json, write_atomic

    if out is not None:
        from station.safeio import check_destination

        check_destination(out, {"--samples": samples})
    res = evaluate_file(samples, direction=direction, pair=pair, level=confidence, noise=noise)
    print_result(res)
    if out is not None:
        write_atomic(out, dumps_json(res) + "\n", {"--samples": samples})
        typer.echo(f"result: {out}")


def register(app: typer.Typer) -> None:
    app.command("iso9283")(iso9283)
