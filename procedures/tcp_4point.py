"""TCP 4-point: touch one fixed point with the tool tip in several orientations and identify the tool offset.

Seed 001 (SCARA 4-point method, generalised): the tip rests on one point C at different flange rotations;
tool offset and C are solved together. On a SCARA the rotations are about one vertical axis, so the tool
length cannot be separated from the height of C and is reported unidentifiable. Works on 6-axis arms too."""

from station.engine.declare import HOLDOUT, POSES, REFERENCE, SEED, SOLVE, measures, takes

IDENTIFY = "tcp"
DEFAULTS = {"n_fit": 8, "n_holdout": 2}


@measures(*SOLVE, judged=("fit_rms",))
@takes(POSES, HOLDOUT, SEED, REFERENCE)  # the cone is its own: 40 deg
def checklist(s):
    s.connect()                                  # 1. connect and identify
    s.check_state()                              # 2. state OK
    point = (s.cell.of_kind("socket") if s.cell else []) or s.points()   # 3. the reference (socket if any)
    plan = s.plan(point[:1], identify=IDENTIFY, cone_deg=40.0)          # 4. tool orientations spread out
    for pose in s.todo(plan):
        s.approach(pose)
        s.seat(pose)                             # 5. tip onto the point (seating, contact or technician)
        s.record(pose)
        s.leave(pose)
    s.solve(identify=IDENTIFY, reference="unknown")   # 6. tool offset + point
    s.measure_result()
    s.judge()                                    # 7. verdict (a TCP lives in the controller program: no write)
