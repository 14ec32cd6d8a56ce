"""The choices of an identification (stages, coefficient forms, force associations, spin sources): plain names,
so that ``ttsim fit``'s options are checked without importing JAX."""

STAGES = ("aero", "table", "racket", "residual")
DEFAULT_STAGES = ("aero", "table", "racket")
FORMS = ("drag", "magnus")
#: The aerodynamic forms fitted by default: the C_D table alone, the C_M form kept from the base
#: (on held-out SpinDOE segments the C_M fit makes the flights worse: benchmarks/fit_real.py).
DEFAULT_FORMS = ("drag",)
#: How a segment's velocity is paired with its fitted force: at the effective velocity or averaged.
ASSOCIATIONS = ("v_eff", "averaged")
#: Where a flight segment's spin comes from (``ttsim evaluate / fit / diagnose --spin``): the measured
#: spin where confident and the latent spin elsewhere, the measured only, the latent everywhere, 0.
SPIN_SOURCES = ("auto", "measured", "latent", "zero")
#: Shortest segment whose latent spin is fitted (shorter ones fly with spin 0).
LATENT_MIN_SAMPLES = 8
