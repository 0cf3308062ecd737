"""Full kinematic calibration: touch every reference point of the cell from many poses, identify link geometry.

Seed 002 (DH calibration by tip touch): zero offsets and the link geometry of the model's convention (DH with
Hayati beta where axes are near-parallel) are identified together; every point of the cell is a nuisance
unknown. The tool centre point is solved too where the data need it: the tool is part of the chain the touches
see, and a tool error of a few tenths of a millimetre left at nominal stays in the fit residual (0.43 mm on an
arm whose tool was 0.5 mm off, against 0.016 mm with it). Whether it is needed is the data's call, not a guess:
both fits are made and the tool is kept when it explains significantly more than its extra unknowns would by
chance (an F-test of the nested fits at 0.1 %); otherwise its unknowns would only dilute the geometry's
uncertainty. Where the data cannot tell a tool coordinate from a link length (the last link's ``d`` and the
tool's ``z``) the solver names it unidentifiable, as everything several fixed points cannot show.
``station run dh_full --identify GROUPS`` solves exactly GROUPS. Samples may also carry external instrument
measurements (``s.record(pose, measured=xyz)``), in which case the instrument frame is solved."""

from station.engine import PlanError
from station.engine.declare import PLAN_OPTIONS, SOLVE, WRITE_BACK, measures, takes

IDENTIFY = "offsets,dh,tcp"  # planned for; solved with the tool only where the data need it (tool_needed)
WITHOUT_TOOL = "offsets,dh"
DEFAULTS = {"n_holdout": 6}
MIN_POINTS = 3  # from one or two unknown points most link parameters of a 6R arm stay unobservable


@measures(*SOLVE, *WRITE_BACK, judged=("fit_rms",))
@takes(*PLAN_OPTIONS)
def checklist(s):
    s.connect()                                  # 1. connect and identify
    s.check_state()                              # 2. state OK
    points = (s.cell.of_kind("socket") if s.cell else []) or s.points()   # 3. every reference point
    if len(points) < MIN_POINTS:                 #    (at least three, spread over the workspace)
        raise PlanError(f"dh_full needs at least {MIN_POINTS} reference sockets in the cell, found "
                        f"{len(points)} ({', '.join(p.label for p in points) or 'none'}): from fewer points the "
                        "link geometry is not observable; add sockets or run zero_offsets")
    plan = s.plan(points, identify=IDENTIFY)     # 4. poses spread over all points, ordered for short motion
    for pose in s.todo(plan):
        s.approach(pose)
        s.seat(pose)
        s.record(pose)
        s.leave(pose)
    if s.options.get("identify"):                # 5. offsets + geometry (+ tool where the data need it) + points
        s.solve(identify=IDENTIFY, reference="unknown")
    else:
        rigid = s.solve(identify=WITHOUT_TOOL, reference="unknown")
        if not tool_needed(rigid, s.solve(identify=IDENTIFY, reference="unknown")):
            s.solve(identify=WITHOUT_TOOL, reference="unknown")   # the result of record is the last one
    s.measure_result()
    s.judge()                                    # 6. verdict
    s.write_back()                               # 7. only the joint offsets can be written to the drives


def tool_needed(without, with_tool, alpha: float = 1e-3, tool_unknowns: int = 3) -> bool:
    """Does solving the tool explain significantly more of the touches than its unknowns would by chance?
    F-test: F = ((RSS0 - RSS1) / k) / (RSS1 / dof1) against F(k, dof1) at ``alpha``, k the tool's three position
    unknowns; RSS from each fit's residual sigma and degrees of freedom. k stays 3 when the solver traded link
    lengths the tool cannot be told from for tool coordinates (the fits are then not nested, and a smaller
    residual by the noise's chance must not win)."""
    from scipy.stats import f

    n0, n1 = without.noise.get("dof"), with_tool.noise.get("dof")
    if not (n0 and n1) or not with_tool.trusted:
        return False
    rss0 = without.noise["fitted_m"] ** 2 * n0
    rss1 = with_tool.noise["fitted_m"] ** 2 * n1
    if rss1 <= 0:
        return bool(rss0 > 0)
    return bool((rss0 - rss1) / tool_unknowns / (rss1 / n1) > f.ppf(1 - alpha, tool_unknowns, n1))
