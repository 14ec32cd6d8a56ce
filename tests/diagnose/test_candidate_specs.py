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


def test_the_fitted_parameters_are_declared_with_the_effect():
    """An effect's parameters say how the diagnosis fits them (``Param.fit_scale``, ``fit_start``):
    a declared step of 0 is fitted held at its start (a second descent frees it in the same
    program), an undeclared parameter whose typical value is its neutral one is not fitted, and the
    bumps' centres start at their typical places."""
    from ttsim_jax.effects.base import Param

    flow, flow_c = C.spec("air_flow")
    assert flow.free == ("wind", "gust_amp", "gust_freq", "gust_phase")  # time_origin: not fitted
    assert flow_c["scale"]["wind"] == 0.2 and flow_c["scale"]["gust_freq"] == 0.0
    bumps, bumps_c = C.spec("table_unevenness")
    assert bumps.free == ("center", "amplitude", "width") and bumps_c["scale"]["center"] == 0.3
    typical = fx.effect_class("table_unevenness").PARAMS["center"].typical
    assert bumps_c["start"]["center"].tolist() == [list(c) for c in typical]
    buckling, buckling_c = C.spec("buckling")
    assert buckling_c["scale"]["table_onset"] == 1.0 and buckling_c["start"]["table_onset"] == 5.0
    with pytest.raises(ValueError, match="fit_start"):
        Param("1", 0.0, 1.0, "x", plausible=(0.0, 2.0), fit_start="middle")
