"""TCP circle (XYZR): turn the rotary axis with the tool tip on a fixed point, identify the tool offset.

Seed 003c (XYZR tool self-calibration): at evenly spread angles of the last (rotary) joint the other joints
bring the tip back onto the point; the flange positions lie on a circle around it, whose radius is the
tool's distance from the rotary axis. No external instrument."""

from station.engine.declare import HOLDOUT, POSES, REFERENCE, SOLVE, measures, takes

IDENTIFY = "tcp"
DEFAULTS = {"n_fit": 8, "n_holdout": 2}


@measures(*SOLVE, judged=("fit_rms",))
@takes(POSES, HOLDOUT, REFERENCE)  # angles of the rotary axis: no cone, no random draw
def checklist(s):
    s.connect()                                  # 1. connect and identify
    s.check_state()                              # 2. state OK
    point = (s.cell.of_kind("socket") if s.cell else []) or s.points()
    plan = s.plan(point[:1], identify=IDENTIFY, rotate_joint=-1)   # 3. angles of the rotary axis
    for pose in s.todo(plan):
        s.approach(pose)
        s.seat(pose)                             # 4. tip onto the point at this angle
        s.record(pose)
        s.leave(pose)
    s.solve(identify=IDENTIFY, reference="unknown")   # 5. tool offset (circle radius) + point
    s.measure_result()
    s.judge()                                    # 6. verdict
