"""Verify: touch the reference from held-out poses with the robot's current calibration; no solve.

After a calibration (and write-back) the nominal model must put the tip on the same spot at every touch of
a fixed point. The spread about the point's centroid is judged against ``verify_rms``/``verify_max``."""

from station.engine.declare import CONSISTENCY, PLAN_OPTIONS, measures, takes

DEFAULTS = {"n_fit": 8, "n_holdout": 0, "seed": 17}


@measures(*CONSISTENCY, judged=("verify_rms",))
@takes(*PLAN_OPTIONS)
def checklist(s):
    s.connect()                                  # 1. connect and identify
    s.check_state()                              # 2. state OK
    plan = s.plan(s.points("socket")[:1], identify="offsets")   # 3. poses (a different spread than the fit)
    for pose in s.todo(plan):
        s.approach(pose)
        s.seat(pose)                             # 4. seat and record
        s.record(pose)
        s.leave(pose)
    s.measure_consistency()                      # 5. spread of the tip positions the model computes
    s.judge()                                    # 6. verdict
