"""The paper's open readings as model variants: the other reading of C_D and C_M between reference
speeds, worked by hand from the tables, and model files that extend a bundled model."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.params import ConfigError
from ttsim_jax.physics import aero as A

R = 0.02


@pytest.fixture(scope="module")
def models():
    return {n: load_model(n, dtype=jnp.float64) for n in
            ("conti2026", "conti2026_cd_blended", "conti2026_cm_values", "conti2026_rho1184")}


def _coefficients(model, speed, spin_rate):
    return [float(x) for x in A.coefficients(model.aero, jnp.array([speed, 0.0, 0.0]),
                                             jnp.array([0.0, spin_rate, 0.0]), R)]


@pytest.mark.parametrize("speed, spin_rate", [(10.0, 300.0), (5.0, 100.0), (15.0, 600.0), (25.0, 600.0)])
def test_drag_readings_by_hand(models, speed, spin_rate):
    d = models["conti2026"].aero.drag
    re_ref, sp_tab, cd_tab = (np.asarray(x) for x in (d.re_ref, d.sp, d.cd))
    nu = float(models["conti2026"].aero.nu)
    re, sp = 2 * speed * R / nu, spin_rate * R / speed
    k = min(int(np.searchsorted(re_ref, re)), len(re_ref) - 1)
    s = (re - re_ref[k - 1]) / (re_ref[k] - re_ref[k - 1])  # > 1 above the last reference
    s_bp = min(s, 1.0)
    values = np.interp(sp, sp_tab[k - 1], cd_tab[k - 1]) * (1 - s) + np.interp(sp, sp_tab[k], cd_tab[k]) * s
    blended = np.interp(sp, (1 - s_bp) * sp_tab[k - 1] + s_bp * sp_tab[k], (1 - s) * cd_tab[k - 1] + s * cd_tab[k])
    assert _coefficients(models["conti2026"], speed, spin_rate)[0] == pytest.approx(values, rel=1e-9)
    assert _coefficients(models["conti2026_cd_blended"], speed, spin_rate)[0] == pytest.approx(blended, rel=1e-9)
    assert abs(values - blended) > 1e-4  # the points are chosen where the readings differ


def test_drag_readings_agree_on_the_reference_rows(models):
    d = models["conti2026"].aero.drag
    nu = float(models["conti2026"].aero.nu)
    for re in np.asarray(d.re_ref):
        speed = re * nu / (2 * R)
        for spin_rate in (0.0, 150.0, 400.0):
            a = _coefficients(models["conti2026"], speed, spin_rate)[0]
            assert _coefficients(models["conti2026_cd_blended"], speed, spin_rate)[0] == pytest.approx(a, rel=1e-9)


@pytest.mark.parametrize("speed, spin_rate", [(5.0, 300.0), (2.5, 600.0), (15.0, 600.0)])
def test_magnus_readings_by_hand(models, speed, spin_rate):
    m = models["conti2026"].aero.magnus
    v_ref = np.asarray(m.v_ref)
    co = {k: np.asarray(getattr(m, k)) for k in ("m1", "s", "w_b", "a", "b", "c")}

    def cm(c, w):
        return max(c["m1"] * w + c["s"] if w <= c["w_b"] else (c["a"] * w + c["b"]) * w + c["c"], 0.0)

    k = int(np.searchsorted(v_ref, speed))
    s = (speed - v_ref[k - 1]) / (v_ref[k] - v_ref[k - 1])
    of_coefficients = cm({n: (1 - s) * v[k - 1] + s * v[k] for n, v in co.items()}, spin_rate)
    of_values = (1 - s) * cm({n: v[k - 1] for n, v in co.items()}, spin_rate) \
        + s * cm({n: v[k] for n, v in co.items()}, spin_rate)
    assert _coefficients(models["conti2026"], speed, spin_rate)[1] == pytest.approx(of_coefficients, abs=1e-12)
    assert _coefficients(models["conti2026_cm_values"], speed, spin_rate)[1] == pytest.approx(of_values, abs=1e-12)
    assert abs(of_values - of_coefficients) > 1e-3


def test_variants_differ_from_their_base_only_where_they_say(models):
    base = models["conti2026"]
    for name, model in models.items():
        assert model.name == name
        for a, b in zip(jax.tree.leaves(base), jax.tree.leaves(model)):
            if name == "conti2026_rho1184" and a.shape == () and float(a) == pytest.approx(1.204):
                assert float(b) == pytest.approx(1.184)
            else:
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert type(models["conti2026_cd_blended"].aero.drag) is A.BlendedDragTable
    assert type(models["conti2026_cm_values"].aero.magnus) is A.MagnusValueTable


def test_extends_errors_name_the_file_and_key(tmp_path):
    a, b = tmp_path / "a.toml", tmp_path / "b.toml"
    a.write_text('schema = 1\nextends = "b.toml"\n')
    b.write_text('schema = 1\nextends = "a.toml"\n')
    with pytest.raises(ConfigError, match=r"b\.toml: key 'extends' = 'a\.toml'.*cycle: a\.toml -> b\.toml -> a\.toml"):
        load_model(a)
    b.write_text('schema = 1\nextends = "no_such_model"\n')
    with pytest.raises(ConfigError, match=r"b\.toml: key 'extends' = 'no_such_model'.*unknown model"):
        load_model(a)
    # a variant of a variant, relative to its own folder, overriding a nested entry
    b.write_text('schema = 1\nextends = "conti2026_rho1184"\n[table]\ne0 = { value = 0.9, unit = "1" }\n')
    m = load_model(a)
    assert m.name == "a" and float(m.aero.rho_air) == pytest.approx(1.184) and float(m.table.e0) == pytest.approx(0.9)
    assert float(m.table.mu) == pytest.approx(float(load_model("conti2026").table.mu))
