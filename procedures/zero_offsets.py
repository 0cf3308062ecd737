"""Zero offsets: seat the tool ball in the cell's socket from ~20 poses and identify the joint zero offsets.

End-of-line procedure (docs/procedures.md: tip touch on a fixed reference, position of the reference unknown).
Offsets that a single fixed point cannot show (the base axis, a wrist axis the tip lies on) are reported
unidentifiable, never guessed. Limits: ``procedures/limits.yaml``, section ``zero_offsets`` of the model."""

from station.engine.declare import PLAN_OPTIONS, SOLVE, WRITE_BACK, measures, takes

IDENTIFY = "offsets"
# a 50 deg cone of tool directions: at 35 deg the elbow/wrist zeros of a 6R arm are 2x worse conditioned
# from some start poses (arm6: offset std 0.012 vs 0.0066 deg), failing the 0.01 deg limit
DEFAULTS = {"n_holdout": 4, "cone_deg": 50.0}


@measures(*SOLVE, *WRITE_BACK, judged=("fit_rms",))
@takes(*PLAN_OPTIONS)
def checklist(s):
    s.connect()                                  # 1. connect and identify the robot (serial must match)
    s.check_state()                              # 2. no fault or stop, powered, not compliant
    plan = s.plan(s.points("socket"), identify=IDENTIFY)   # 3. spread of poses around the socket(s)
    for pose in s.todo(plan):                    # 4. every pose not yet recorded:
        s.approach(pose)                         #    move above the socket
        s.seat(pose)                             #    go down, compliant: the ball seats in the cone
        s.record(pose)                           #    read all joints, journal the sample (fsynced)
        s.leave(pose)                            #    compliance off, back above the socket
    s.solve(identify=IDENTIFY)                   # 5. offsets (+ socket position unless --reference cell)
    s.measure_result()                           # 6. residuals, held-out check, offsets vs. limits
    s.judge()                                    # 7. PASS / FAIL
    s.write_back()                               # 8. only with --apply: pre-image, write, read back, verify
