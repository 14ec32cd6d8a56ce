"""The diagnosis on racket contacts measured as states (a rig, no flights): the racket phase is
collected from the contact states, the phases without data are reported as such, and the gap of a
rubber the model does not know is located in the racket phase with its noise floor said to be
unknown (there are no positions to read a noise from)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ttsim_jax.diagnose import phases
from ttsim_jax.diagnose.diagnosis import diagnose
from ttsim_jax.diagnose.report import markdown
from ttsim_jax.params import load_model
from ttsim_jax.reality import synthetic_rig_dataset

SLICK = [0.7, -0.005, 0.2, -0.002, 0.3]  # little grip, as a pimpled rubber: conti2026 overstates it


def test_racket_phase_from_measured_states():
    ds = synthetic_rig_dataset({"slick": SLICK}, 400, seed=2)
    model = load_model("conti2026", dtype=jnp.float32)
    ph = phases.collect(ds, model)
    assert ph.flights is None and ph.table is None and {"flight", "table"} <= set(ph.skipped)
    rk = ph.racket
    assert len(rk.event_id) == 400
    assert np.isnan(rk.since).all() and (rk.spin_dt == 0).all()  # no segments around a rig's contact
    out = diagnose(ds, model)
    assert set(out.no_data) >= {"flight", "table"}
    assert isinstance(out.floor["racket"], str)  # no floor: no positions
    text = out.verdict.text
    assert "racket" in text and "0 m/s" not in text
    assert out.verdict.level != "explained"
    text = markdown(out, "rig", "conti2026")
    assert "nan" not in text.lower().replace("nakashima", "")  # nothing unknown is printed as a number
