"""The catalogue's lab-condition effects as diagnosis candidates: the simulator ones are fitted in
the phases they act in, at steps that reach their plausible ranges; the record ones are not fitted."""

import pytest

from ttsim_jax import effects as fx
from ttsim_jax.diagnose import candidates as C


def test_air_density_and_table_friction_are_candidates_in_their_phases():
    names = C.candidate_names()
    assert {"air_density", "table_friction"} <= set(names)
    assert not {"clock_rate", "camera_scale"} & set(names)
    air, air_c = C.spec("air_density")
    assert (air.phases, air.free, air.per_session) == (("flight",), ("d_rho",), True)
    assert C.spec("air_density", pooled=True)[0].per_session is False
    assert air_c["start"]["d_rho"] == 0.0 and air_c["scale"]["d_rho"] == 0.1
    table, table_c = C.spec("table_friction")
    assert (table.phases, table.free, table.per_session) == (("table",), ("d_mu",), False)
    assert table_c["start"]["d_mu"] == 0.0 and table_c["scale"]["d_mu"] == 0.2
    spinning, flight, other = C.groups(names, C.PHASES)
    assert "air_density" in flight and "table_friction" in other
    # an effect that changes the spin in flight makes every flight of its program fly twice
    assert "spin_decay" in spinning and "spin_decay" not in flight


@pytest.mark.parametrize("name", ["clock_rate", "camera_scale"])
def test_record_effects_are_not_fitted(name):
    assert fx.effect_class(name).WHERE == "record"
    with pytest.raises(fx.EffectError, match="acts on the record"):
        C.spec(name)
