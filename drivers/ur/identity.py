"""Which UR arm a kinematic model is for, and the check against what the controller reports.

The dashboard server reports the robot type (``get robot model``: ``UR3``, ``UR5``, ``UR10``, ``UR16``, ``UR20``,
``UR30``; the same word on CB3 and e-Series) and the software version (``PolyscopeVersion``: ``URSoftware
3.x`` on CB3, ``5.x`` on e-Series, ``10.x`` PolyScope X on e-Series / UR Series). Type + series together
name the arm whose published DH table the model must be: a UR3e model on a UR5e, or a CB3 table on an
e-Series arm, moves the robot to wrong poles, so a mismatch refuses to connect."""

from __future__ import annotations

import re

from station.robot.errors import IdentityMismatch

# UR20 and UR30 have no "e" in their name but are e-Series generation arms (PolyScope 5.x / X)
_NAME = re.compile(r"^ur(\d{1,2})(e?)$", re.IGNORECASE)
E_SERIES_ONLY = {"20", "30"}


def expected_arm(model_name: str, robot_type: str | None) -> tuple[str, str] | None:
    """``("UR5", "e-Series")`` for a model named ``ur5e`` (or ``robot_type=UR5e``); None if neither names a
    UR arm."""
    m = _NAME.match((robot_type or model_name).strip())
    if not m:
        return None
    size, e = m.groups()
    return f"UR{size}", "e-Series" if (e or size in E_SERIES_ONLY) else "CB3"


def series_of(polyscope: str) -> str | None:
    """``e-Series`` / ``CB3`` from the ``PolyscopeVersion`` reply (None when it names no version)."""
    m = re.search(r"(\d+)\.(\d+)", polyscope)
    if not m:
        return None
    major = int(m.group(1))
    return "CB3" if major < 5 else "e-Series"


def _builtin_for(arm: str) -> str | None:
    """The built-in model of a controller's arm (``UR5e`` -> ``ur5e``), if the station ships one."""
    from station.kinematics import builtin_names

    name = arm.split()[0].lower()
    return name if name in builtin_names() else None


def check_arm(host: str, model_name: str, robot_type: str | None, reported_type: str, polyscope: str) -> str:
    """The controller's arm as ``UR5e`` / ``UR5 (CB3)``; ``IdentityMismatch`` (one line naming the fix that
    works) when it is not the arm the model is for."""
    rep_type = reported_type.strip().upper()
    rep_series = series_of(polyscope)
    shown = f"{rep_type}{'e' if rep_series == 'e-Series' and rep_type[2:] not in E_SERIES_ONLY else ''}" + (
        " (CB3)" if rep_series == "CB3" else "")
    arm = shown.split()[0]  # what robot_type= takes for this controller: UR5e, UR10, UR20
    builtin = _builtin_for(arm)
    if not re.fullmatch(r"UR\d{1,2}", rep_type):
        raise IdentityMismatch(f"ur://{host}: the controller reports robot model {reported_type!r}, not a UR arm; "
                               "nothing was moved")
    want = expected_arm(model_name, robot_type)
    if want is None:
        if robot_type:
            raise IdentityMismatch(f"ur://{host}: robot_type={robot_type} names no UR arm; the controller is a "
                                   f"{shown}: use robot_type={arm} (if model {model_name} describes this arm)")
        instead = f", or model={builtin} for the published {arm}" if builtin else ""
        raise IdentityMismatch(f"ur://{host}: model {model_name} does not say which UR arm it is for; the "
                               f"controller is a {shown}: add robot_type={arm} to the robot URL if {model_name} "
                               f"describes this arm{instead}; nothing was moved")
    if rep_type != want[0] or (rep_series is not None and rep_series != want[1]):
        source = f"robot_type={robot_type}" if robot_type else f"model {model_name}"
        if robot_type:
            fix = f"use robot_type={arm} only if model {model_name} describes this arm"
        elif builtin:
            fix = f"use model={builtin}"
        else:
            fix = f"use a model of this arm (a model file with robot_type={arm})"
        raise IdentityMismatch(f"ur://{host}: {source} is a {want[0]} {want[1]} but the controller reports "
                               f"{rep_type} {rep_series or '(series unknown)'} ({polyscope.strip()!r}); nothing "
                               f"was moved: {fix}")
    return shown
