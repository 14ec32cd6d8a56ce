"""The diagnosis's default settings and thresholds: plain numbers, so that ``ttsim diagnose
--help`` states them (and the options are checked) before JAX is imported."""

#: Flight segments used at most (a seeded random subset of more): None, every segment (a lab that
#: recorded 2,000 expects them all to count; ``--max-segments`` is the opt-out for speed).
MAX_SEGMENTS = None
#: Adam steps per candidate and the initial step size (units of each parameter's scale).
STEPS, LEARNING_RATE = 100, 0.1
#: Share of the segments and contacts held out for scoring.
TEST_FRACTION = 0.4
#: What ``--quick`` changes: fewer steps and segments, no landing rollouts, no joint fit, no spin
#: check of the record.
QUICK = dict(steps=60, landing=False, combine=False, max_segments=96, spin_check=False)
#: Least held-out reduction [%] (lower end of the 95 % interval) of a significant candidate.
MIN_REDUCTION = 1.0
#: A bin stands out when its interval's lower end exceeds this times the phase's mean error.
FLAG_RATIO = 1.25
