"""Full kinematic calibration: touch every reference point of the cell from many poses, identify link geometry.

Seed 002 (DH calibration by tip touch): zero offsets and the link geometry of the model's convention (DH with
Hayati beta where axes are near-parallel) are identified together; every point of the cell is a nuisance
unknown. What several fixed points cannot show is named unidentifiable. Samples may also carry external
instrument measurements (``s.record(pose, measured=xyz)``), in which case the instrument frame is solved."""

IDENTIFY = "offsets,dh"
DEFAULTS = {"n_holdout": 6}


def checklist(s):
    s.connect()                                  # 1. connect and identify
    s.check_state()                              # 2. state OK
    points = (s.cell.of_kind("socket") if s.cell else []) or s.points()   # 3. every reference point
    plan = s.plan(points, identify=IDENTIFY)     # 4. poses spread over all points, ordered for short motion
    for pose in s.todo(plan):
        s.approach(pose)
        s.seat(pose)
        s.record(pose)
        s.leave(pose)
    s.solve(identify=IDENTIFY, reference="unknown")   # 5. offsets + geometry + points
    s.measure_result()
    s.judge()                                    # 6. verdict
    s.write_back()                               # 7. only the joint offsets can be written to the drives
