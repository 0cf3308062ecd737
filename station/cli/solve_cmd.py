"""``station solve`` (identify parameters from touch samples) and ``station fk`` (tool poses from joint
readings with the nominal or a calibrated model). Public interface: factory scripts depend on it."""

from __future__ import annotations

import csv
import io
import math
import re
import sys
from pathlib import Path

from station.cli.model_options import MODEL_OPTIONS
from station.cli.optspec import REQUIRED, Opt, click_command
from station.lazy import lazy_module
from station.quantity import parse_xyz
from station.robot.errors import ConfigError
from station.samplesfile import SamplesFileError, read_joints, read_samples

np = lazy_module("numpy")  # imported on first use (station.lazy: start-up of every command)


def _fail(msg: str) -> ConfigError:
    """The one-line error to raise: station.cli.main prints ``station: error: MSG`` and exits 2."""
    return ConfigError(msg)


def _load_model(name: str, tool: str | None, tip_link: str | None = None, base_link: str | None = None,
                payload: str | None = None):
    from station.cli.model_options import load_cli_model

    model = load_cli_model(name, tip_link, base_link, payload)  # ModelFileError -> one-line error, exit 2
    if tool:
        t = parse_xyz(tool, "--tool")
        model = model.with_params({"tcp.x": t[0], "tcp.y": t[1], "tcp.z": t[2]})
    return model


def _references(specs: list[str], labels: list[str], samples: str):
    if not specs or specs == ["unknown"]:
        return "unknown"
    ref: dict[str, np.ndarray] = {}
    seen: set[str] = set()
    for s in specs:
        key = s.split("=", 1)[0].strip() if "=" in s else ""
        if key in seen:
            raise _fail(f"--reference {s!r}: point {key or '(the only point)'!r} is given twice; give each once")
        seen.add(key)
        if s == "unknown":
            raise _fail("--reference unknown cannot be combined with known points")
        if "=" in s:
            label, xyz = s.split("=", 1)
            ref[label.strip()] = parse_xyz(xyz, "--reference")
        else:
            if len(labels) != 1:
                raise _fail(f"--reference {s!r}: {samples} touches points {', '.join(labels)}; "
                            f"give LABEL=x,y,z for each known one")
            ref[labels[0]] = parse_xyz(s, "--reference")
    unknown = [lb for lb in ref if lb not in labels]
    if unknown:
        raise _fail(f"--reference: point {unknown[0]!r} is not in {samples} (points: {', '.join(labels)})")
    return ref


def check_max_std(max_std) -> float | None:
    """``--max-std 1mm`` (a length at the tool; a bare number is metres): 0, negative or non-finite would switch
    identifiability off. None (not given): the priors decide what the data determine (docs/solver.md, section 3).
    Returns metres."""
    if max_std is None:
        return None
    from station.quantity import parse_option

    value = parse_option(max_std, "--max-std", "length", "m", "1mm")
    if not 0 < value <= 1.0:
        raise _fail(f"--max-std {max_std!r}: expected a positive length of at most 1 m, e.g. 1mm (a bare number is "
                    "metres: 0.001)")
    return value


def check_identify(identify: str) -> str:
    if not identify.strip() or not all(p.strip() for p in identify.split(",")):
        raise _fail(f"--identify {identify!r}: expected groups/names/globs separated by commas, e.g. offsets,tcp")
    return identify


def _fmt(p) -> tuple[str, str, str]:
    """Value, std and unit for humans: mm / deg / urad/(N m)."""
    from station.solver.problem import human_unit  # numpy: imported on first use
    k, unit = human_unit(p.unit)
    val = "-" if not math.isfinite(p.value) else f"{p.value * k:+.4f}"
    std = "-" if p.std is None else f"{p.std * k:.4f}"
    return val, std, unit


def summary(res) -> str:
    lines = [f"model {res.model}: {res.n_samples} samples, {res.n_parameters} unknowns, rank {res.rank}, "
             f"{'converged' if res.converged else 'NOT CONVERGED'} in {res.iterations} iterations"]
    cond = "-" if res.condition_number is None else f"{res.condition_number:.3g}"
    o1 = "-" if res.observability_index is None else f"{res.observability_index:.3g}"
    lines.append(f"condition number {cond}, observability index O1 {o1}, residual sigma "
                 f"{(res.sigma_m or 0) * 1e3:.4f} mm")
    r = res.residuals
    lines.append(f"residual RMS {r['rms_before_m'] * 1e3:.4f} mm -> {r['rms_after_m'] * 1e3:.4f} mm "
                 f"(max {r['max_after_m'] * 1e3:.4f} mm)")
    if res.holdout:
        h = res.holdout
        lines.append(f"holdout ({h['n_samples']} samples): RMS {h['rms_m'] * 1e3:.4f} mm, max {h['max_m'] * 1e3:.4f} "
                     f"mm (nominal model {h['rms_nominal_m'] * 1e3:.4f} mm)")
    lines.append(f"{'parameter':<16} {'value':>12} {'std':>10}  {'unit':<10} prior")
    for n, p in res.parameters.items():
        if p.identifiable:
            val, std, unit = _fmt(p)
            # the prior's share of what is known of the parameter: 0 % the data alone, "freed" a prior the data
            # contradicted (estimated from the data alone), "-" no prior (points, instrument frame)
            share = "-" if p.prior_share is None else f"{100 * p.prior_share:.0f} %"
            if any(c.get("parameter") == n and c.get("freed") for c in res.conflicts):
                share = "freed"
            lines.append(f"{n:<16} {val:>12} {std:>10}  {unit:<10} {share}")
    if res.constraints:
        lines.append("constraints:")
        lines += constraint_lines(res)
    bad = res.unidentifiable
    if bad:
        lines.append("not identifiable (kept at nominal):")
        lines += [f"  {n}: {why}" for n, why in bad.items()]
    if res.outliers:
        lines.append(f"outliers excluded ({len(res.outliers)}):")
        lines += [f"  row {o['index'] + 1} point {o['point']}: {o['residual_m'] * 1e3:.4f} mm" for o in res.outliers]
    lines += [f"note: {n}" for n in res.notes]
    t = "" if res.solve_time_s is None else f" (solve {res.solve_time_s * 1e3:.1f} ms)"
    lines.append(("result: trusted" if res.trusted else f"result: NOT TRUSTED: {res.failure}") + t)
    return "\n".join(lines)


SOLVE_OPTIONS = [
    *MODEL_OPTIONS,
    Opt("samples", "--samples", "CSV: q1..qN [point] [x,y,z]; units in headers", REQUIRED, Path),
    Opt("identify", "--identify", "Groups/names/globs, e.g. offsets,tcp,dh", "offsets,tcp"),
    Opt("reference", "--reference", "Reference points: unknown (solved, the default), x,y,z of the one point (m, "
        "or a unit suffix: 412,-120,35mm) or LABEL=x,y,z (repeatable)", multiple=True),
    Opt("tool", "--tool", "Nominal TCP x,y,z in the flange frame (m, or suffix mm)"),
    Opt("holdout", "--holdout", "CSV of validation samples (same columns), or fixture=F1[,F2] / point=A[,B]: hold "
        "out the samples' rows of those fixture positions (or points) and score the fit on them", kind=Path),
    Opt("out", "--out", "Write the result JSON here", kind=Path),
    Opt("instrument_frame", "--instrument-frame", "With x,y,z columns: unknown (the instrument frame is solved) "
        "or base", "unknown"),
    Opt("max_std", "--max-std", "A length at the tool (1mm; a bare number is metres): also leave at nominal what the "
        "data leave a larger std than this (default: none, a parameter the data determine to within its prior is "
        "estimated)"),
    Opt("prior", "--prior", "SELECTOR=STD with a unit, e.g. offsets=0.5deg, dh=0.3mm, dh.j2.a=0.1mm, "
        "compliance=1e-4rad/Nm (repeatable; overrides the model file's tolerances)", multiple=True),
    Opt("noise", "--noise", "Declared touch noise per axis with a unit, e.g. 20um (default: fitted from the "
        "residual of the fitted model)"),
    Opt("loss", "--loss", "Loss: linear (outliers beyond 4 sigma excluded), huber or soft_l1", "linear"),
    Opt("distance", "--distance", "A,B=50mm[±0.01mm]: the measured distance between points A and B (repeatable; "
        "default uncertainty 0.01 mm)", multiple=True),
    Opt("plane", "--plane", "LABEL: the touches labelled LABEL lie on one unknown plane (touch-probing a flat "
        "surface; repeatable)", multiple=True),
    Opt("touch", "--touch", "How the tip meets the points: socket (a seated ball) | needle (aligned by eye); a fit "
        "far above what that gives is not trusted and says why", "socket"),
]


def solve_command(model: str, tip_link: str | None, base_link: str | None, payload: str | None, samples: Path,
                  identify: str, reference: tuple[str, ...], tool: str | None, holdout: Path | None,
                  out: Path | None, instrument_frame: str, max_std: str | None, prior: tuple[str, ...],
                  noise: str | None, loss: str, distance: tuple[str, ...], plane: tuple[str, ...],
                  touch: str = "socket") -> None:
    """Identify joint offsets, TCP, link geometry from touch samples. Exit 0: trusted result; 1: the solve
    failed or its result cannot be trusted (one line says why; the JSON is still written); 2: bad input."""
    from station.safeio import dumps_json, write_atomic
    from station.solver import Observations, SolverInputError, solve

    max_std = check_max_std(max_std)
    check_identify(identify)
    if out is not None:  # refuse a bad destination before the work, not after
        write_atomic_check(out, {"--samples": samples, "--holdout": holdout})
    priors, noise_m = _priors(list(prior or [])), _noise(noise)
    distances = [parse_distance(d) for d in distance or []]
    planes = [_plane_label(p) for p in plane or []]
    if loss not in ("linear", "huber", "soft_l1"):
        raise _fail(f"--loss {loss!r}: expected linear, huber or soft_l1")
    if touch not in ("socket", "needle"):
        raise _fail(f"--touch {touch!r}: expected socket or needle (instrument samples are judged as a tracker's)")

    m = _load_model(model, tool, tip_link, base_link, payload)
    from station.cli.model_options import warn_lines

    group = _holdout_group(holdout)
    try:
        s = read_samples(samples, m)
        obs = Observations(s.q, s.point, s.measured, s.weight, s.fixture)
        ho = None
        if holdout is not None and group is None:
            h = read_samples(holdout, m)
            ho = Observations(h.q, h.point, h.measured, h.weight, h.fixture)
            s.warnings += h.warnings
    except SamplesFileError as e:
        raise _fail(str(e)) from None
    warn_lines(s.warnings)
    if group is not None:
        obs, ho = split_holdout(obs, group, str(samples))
    if instrument_frame not in ("unknown", "base"):
        raise _fail(f"--instrument-frame {instrument_frame!r}: expected unknown or base")
    ref = _references(list(reference or []), obs.labels, str(samples))
    if s.measured is not None and ref != "unknown":
        raise _fail(f"--reference: {samples} has instrument columns x,y,z; known points are not used with them")
    try:
        res = solve(m, obs, identify, ref, ho, instrument_frame=instrument_frame, max_std=max_std,
                    noise=noise_m, priors=priors, loss=loss, distances=distances or None, planes=planes or None,
                    touch=touch)
    except SolverInputError as e:
        raise _fail(_input_error(str(e), identify, samples)) from None
    _diagnose(res, m, obs, s, str(samples), noise_m,
              lambda o: solve(m, o, identify, ref, None, instrument_frame=instrument_frame, max_std=max_std,
                              noise=noise_m, priors=priors, loss=loss, distances=distances or None,
                              planes=planes or None, touch=touch))
    res.settings.update(samples=str(samples), holdout=None if holdout is None else str(holdout), tool=tool,
                        payload=_payload_setting(payload))
    print(summary(res), flush=True)
    if out is not None:
        write_atomic(out, dumps_json(res.to_dict()) + "\n", {"--samples": samples, "--holdout": holdout})
        print(f"result: {out}", flush=True)
    if not res.trusted:
        print(f"station: solve failed: {res.failure or 'result not trusted'}", file=sys.stderr, flush=True)
        sys.exit(1)


def _input_error(msg: str, identify: str, samples: Path) -> str:
    """The solver's refusal, named by the option (or the file) it came from."""
    for option in ("distance", "plane", "prior"):
        if msg.startswith(f"{option} "):
            return f"--{option}: {msg}"
    if "parameter or group" in msg or msg.startswith("compliance."):
        return f"--identify {identify!r}: {msg}"
    return f"{samples}: {msg}"


_GROUP = re.compile(r"^(fixture|point)=([A-Za-z0-9_-]+(?:,[A-Za-z0-9_-]+)*)$")


def _holdout_group(holdout: Path | None) -> tuple[str, list[str]] | None:
    """``--holdout fixture=2,3`` / ``point=C``: (column, labels); None for a file (an existing file wins)."""
    if holdout is None or holdout.exists():
        return None
    m = _GROUP.match(str(holdout))
    return None if m is None else (m.group(1), m.group(2).split(","))


def split_holdout(obs, group: tuple[str, list[str]], samples: str):
    """(fit, held out) by a label group of the samples: the rows of fixture positions (or points) ``labels`` are
    left out of the fit and scored on it. Held-out fixture positions are new places: their points are scored by
    consistency (their touches must meet), each position on its own."""
    import numpy as np

    from station.solver import Observations

    col, labels = group
    have = obs.fixture if col == "fixture" else obs.point
    if have is None:
        raise _fail(f"--holdout {col}=...: {samples} has no '{col}' column")
    known = sorted(set(have.astype(str).tolist()))
    missing = [lb for lb in labels if lb not in known]
    if missing:
        raise _fail(f"--holdout {col}={','.join(labels)}: no {col} {missing[0]!r} in {samples} ({col}s: "
                    f"{', '.join(known)})")
    out = np.isin(have.astype(str), labels)
    if out.all():
        raise _fail(f"--holdout {col}={','.join(labels)}: that is every row of {samples}; nothing left to fit")
    fit, ho = obs.subset(~out), obs.subset(out)
    if ho.fixture is not None:  # each held-out position's points are its own: LABEL@FIXTURE
        ho = Observations(ho.q, np.array([f"{p}@{f}" for p, f in zip(ho.point, ho.fixture, strict=True)],
                                         dtype=object), ho.measured, ho.weight, None)
    return fit, ho


def _payload_setting(payload: str | None) -> dict | None:
    """``--payload`` as the result records it (SI): the compliance terms of a result hold only under this load,
    so whoever uses the result (``station run correction_map --calibration``) can check it is the same."""
    if not payload:
        return None
    from station.quantity import parse_payload

    mass, com = parse_payload(payload)
    return {"mass": float(mass), "com": [float(c) for c in com]}


_DISTANCE = re.compile(r"^\s*([A-Za-z0-9_-]+)\s*,\s*([A-Za-z0-9_-]+)\s*=\s*([^±]+?)\s*(?:(?:±|\+-|\+/-)\s*(.+?))?\s*$")


def parse_distance(text: str) -> tuple[str, str, float, float | None]:
    """``--distance A,B=50mm`` or ``A,B=50mm±0.01mm`` (also ``+-``): (a, b, metres, std metres or None)."""
    from station.kinematics.tolerances import parse_quantity

    m = _DISTANCE.match(text)
    if not m:
        raise _fail(f"--distance {text!r}: expected A,B=LENGTH[±STD], e.g. A,B=50mm or A,B=50mm±0.01mm")
    a, b, val, sd = m.groups()
    if a == b:
        raise _fail(f"--distance {text!r}: the two points must differ")
    out = []
    for part in (val, sd):
        if part is None:
            out.append(None)
            continue
        part = part.strip()
        if re.fullmatch(r"[-+]?[0-9.]+(?:[eE][-+]?[0-9]+)?", part) and val.strip() != part:
            part += re.sub(r"^[-+0-9.eE]+", "", val.strip())  # a bare uncertainty takes the distance's unit
        try:
            v, q = parse_quantity(part)
        except ValueError as e:
            raise _fail(f"--distance {text!r}: {e}") from None
        if q != "length" or not v > 0:
            raise _fail(f"--distance {text!r}: {part!r} must be a positive length (m, mm, cm, um)")
        out.append(v)
    return a, b, out[0], out[1]


def _plane_label(text: str) -> str:
    if not re.fullmatch(r"[A-Za-z0-9_-]+", text.strip()):
        raise _fail(f"--plane {text!r}: expected a point label (letters, digits, _ or -)")
    return text.strip()


def constraint_lines(res) -> list[str]:
    """The known distances and planes of a result, for people (mm)."""
    out = []
    for c in res.constraints:
        where = f" @{c['fixture']}" if c.get("fixture") else ""
        if c["kind"] == "distance":
            fs = "" if c.get("fitted_std_m") is None else f" ± {c['fitted_std_m'] * 1e3:.4f}"
            out.append(f"  distance {','.join(c['labels'])}{where}: stated {c['stated_m'] * 1e3:.4f} ± "
                       f"{c['stated_std_m'] * 1e3:.4f} mm, fitted {c['fitted_m'] * 1e3:.4f}{fs} mm, residual "
                       f"{c['residual_m'] * 1e3:+.4f} mm")
        elif c["kind"] == "plane":
            n = ", ".join(f"{v:+.5f}" for v in c["normal"])
            rms = "-" if c.get("residual_m") is None else f"{c['residual_m'] * 1e3:.4f}"
            mx = "-" if c.get("max_residual_m") is None else f"{c['max_residual_m'] * 1e3:.4f}"
            out.append(f"  plane {c['labels'][0]}{where}: normal ({n}), offset {c['offset_m'] * 1e3:.4f} mm, "
                       f"{c['n_touches']} touches, residual RMS {rms} mm (max {mx} mm)")
    return out


def _diagnose(res, model, obs, s, samples: str, noise_m: float | None, refit) -> None:
    """Post-fit checks (station.solver.diagnose): a unit slip inside the joint limits is bad input (exit 2,
    naming the column or row); noise-free data leave the ± not estimable (not trusted, exit 1)."""
    from station.solver.diagnose import noise_free, unit_slip

    slip = unit_slip(model, obs, res, refit, noise_m, samples, s.lines)
    if slip is not None:
        raise _fail(slip.message())
    why = noise_free(res, noise_m)
    if why is not None:  # no ± at all rather than a ± of 0: std and covariance are null, the result not trusted
        import dataclasses

        res.parameters = {n: dataclasses.replace(p, std=None) for n, p in res.parameters.items()}
        res.covariance = None
        res.trusted, res.failure = False, why if not res.failure else f"{why}; {res.failure}"


def _priors(specs: list[str]) -> list[tuple[str, float, str]] | None:
    """``--prior SELECTOR=STD``: (selector, std SI, quantity)."""
    from station.kinematics.tolerances import parse_quantity

    out = []
    for spec in specs:
        sel, eq, val = spec.partition("=")
        if not eq or not sel.strip():
            raise _fail(f"--prior {spec!r}: expected SELECTOR=STD with a unit, e.g. offsets=0.5deg or dh=0.3mm")
        try:
            v, q = _compliance_quantity(val) or parse_quantity(val)
        except ValueError as e:
            raise _fail(f"--prior {spec!r}: {e}") from None
        if v <= 0:
            raise _fail(f"--prior {spec!r}: the standard deviation must be > 0")
        out.append((sel.strip(), v, q))
    return out or None


def _compliance_quantity(text: str) -> tuple[float, str] | None:
    """``1e-4rad/Nm`` (also ``rad/(N m)``, ``urad/Nm``): a joint compliance prior, rad per N m; else None."""
    t = text.replace(" ", "").replace("(", "").replace(")", "").replace("*", "")
    for suffix, k in (("urad/Nm", 1e-6), ("mrad/Nm", 1e-3), ("rad/Nm", 1.0)):
        if t.endswith(suffix):
            try:
                v = float(t[: -len(suffix)]) * k
            except ValueError:
                raise ValueError(f"{text!r}: expected a number before {suffix}") from None
            if not math.isfinite(v):
                raise ValueError(f"{text!r}: not a finite number")
            return v, "compliance"
    return None


def _noise(text: str | None) -> float | None:
    """``--noise 20um``: declared isotropic touch noise per axis, m."""
    if text is None:
        return None
    from station.kinematics.tolerances import parse_quantity

    try:
        v, q = parse_quantity(text)
    except ValueError as e:
        raise _fail(f"--noise {e}") from None
    if q != "length" or v <= 0:
        raise _fail(f"--noise {text!r}: expected a positive length, e.g. 20um or 0.02mm")
    return v


FK_OPTIONS = [
    *MODEL_OPTIONS,
    Opt("joints", "--joints", "CSV with q1..qN (units in headers: q1[deg], q3[mm])", REQUIRED, Path),
    Opt("calibration", "--calibration", "Result JSON of station solve", kind=Path),
    Opt("tool", "--tool", "Nominal TCP x,y,z (m, or suffix mm), before the calibration"),
    Opt("out", "--out", "Write CSV here (default: stdout)", kind=Path),
]


def fk_command(model: str, tip_link: str | None, base_link: str | None, payload: str | None, joints: Path,
               calibration: Path | None, tool: str | None, out: Path | None) -> None:
    """Tool pose (x, y, z in m; rx, ry, rz rotation vector in rad) for each row of joint readings."""
    from station.kinematics import se3
    from station.safeio import write_atomic

    inputs = {"--joints": joints, "--calibration": calibration}
    if out is not None:
        write_atomic_check(out, inputs)
    m = _load_model(model, tool, tip_link, base_link, payload)
    if calibration is not None:
        from station.resultfile import load_calibration  # pydantic: only with a calibration

        m = load_calibration(calibration, m)
    try:
        q, table = read_joints(joints, m)
    except SamplesFileError as e:
        raise _fail(str(e)) from None
    from station.cli.model_options import warn_lines

    warn_lines(table.warnings)
    pose = se3.matrix_to_pose(m.fk(q).reshape(-1, 4, 4), "rotvec")
    header = ["x[m]", "y[m]", "z[m]", "rx[rad]", "ry[rad]", "rz[rad]"]
    buf = io.StringIO()
    buf.write(f"# station fk: model {m.name}, "
              f"{'calibration ' + str(calibration) if calibration else 'nominal'}; rotation vector\n")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for row in pose:
        w.writerow([f"{v:.9f}" for v in row])
    if out is None:
        sys.stdout.write(buf.getvalue())
    else:
        write_atomic(out, buf.getvalue(), inputs)


def write_atomic_check(out: Path, inputs: dict) -> None:
    """Refuse ``--out`` early: an input file, a directory or a missing folder (nothing written)."""
    from station.safeio import check_destination

    check_destination(out, inputs)


def click_commands() -> dict:
    """``solve`` and ``fk`` as plain click commands (station.cli.optspec says why not typer)."""
    return {"solve": click_command("solve", solve_command, SOLVE_OPTIONS),
            "fk": click_command("fk", fk_command, FK_OPTIONS)}
