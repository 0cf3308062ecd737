"""Full kinematic calibration: touch every reference point of the cell from many poses, identify link geometry.

Seed 002 (DH calibration by tip touch): zero offsets, the link geometry of the model's convention (DH with
Hayati beta where axes are near-parallel) and the tool centre point are identified together; every point of the
cell is a nuisance unknown. The tool is part of the chain the touches see: left at nominal, a tool error of a
few tenths of a millimetre would stay in the fit residual (or bend the link geometry to mimic it); where the
data cannot tell a tool coordinate from a link length (the last link's ``d`` and the tool's ``z``) the solver
names it unidentifiable and keeps it at nominal, as everything several fixed points cannot show. Samples may
also carry external instrument measurements (``s.record(pose, measured=xyz)``), in which case the instrument
frame is solved."""

from station.engine import PlanError

IDENTIFY = "offsets,dh,tcp"
DEFAULTS = {"n_holdout": 6}
MIN_POINTS = 3  # from one or two unknown points most link parameters of a 6R arm stay unobservable


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
    s.solve(identify=IDENTIFY, reference="unknown")   # 5. offsets + geometry + tool + points
    s.measure_result()
    s.judge()                                    # 6. verdict
    s.write_back()                               # 7. only the joint offsets can be written to the drives
