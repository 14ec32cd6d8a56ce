import re
import tomllib

import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import ConfigError, load_model
from ttsim_jax.params import config_dir, model_from_dict

CONTI = config_dir() / "models" / "conti2026.toml"


def conti_dict():
    return tomllib.loads(CONTI.read_text())


@pytest.mark.parametrize("name", ["nakashima2011", "durr2026", "conti2026"])
def test_bundled_models_load(name):
    m = load_model(name)
    assert m.name == name
    assert float(m.ball.radius) == pytest.approx(0.02)


def test_conti_holds_every_number_of_the_paper():
    m = load_model("conti2026", dtype=jnp.float64)
    assert np.asarray(m.aero.drag.cd)[2].tolist() == [0.47, 0.47, 0.53, 0.41, 0.48, 0.48]
    assert np.asarray(m.aero.drag.sp)[3].tolist() == [0.0, 0.4, 0.5, 0.84, 1.2, 2.0]
    assert np.asarray(m.aero.magnus.w_b).tolist() == [150, 200, 350, 440, 550, 650]
    assert float(m.aero.magnus.a[4]) == -3.571e-7
    assert float(m.table.residual[2, 0, 2]) == -1.02984
    assert float(m.table.residual[0, 1, 2]) == 3.378e-3
    assert (float(m.racket.e0), float(m.racket.e1), float(m.racket.et0), float(m.racket.et1), float(m.racket.e_s)) == (
        0.878, -0.020, 0.819, -0.010, 0.805)
    text = CONTI.read_text()
    # every number carries a unit
    for line in text.splitlines():
        if re.match(r"^\w+ = \{ value", line):
            assert "unit =" in line or line.rstrip().endswith("[")


def expect_error(data, *fragments):
    with pytest.raises(ConfigError) as info:
        model_from_dict(data, "my_model.toml")
    msg = str(info.value)
    assert "my_model.toml" in msg
    for frag in fragments:
        assert frag in msg, msg


def test_unknown_key_names_file_key_and_value():
    d = conti_dict()
    d["table"]["mue"] = 0.3
    expect_error(d, "table.mue", "0.3", "unknown key")


def test_missing_key():
    d = conti_dict()
    del d["ball"]["mass"]
    expect_error(d, "ball.mass", "missing")


@pytest.mark.parametrize("section,key,value", [
    ("ball", "radius", -0.02), ("ball", "mass", -1.0), ("table", "mu", -0.1), ("table", "e0", 1.3),
    ("racket", "e0", -0.2), ("racket", "e_s", 1.5)])
def test_non_physical_values(section, key, value):
    d = conti_dict()
    d[section][key] = {"value": value, "unit": d[section][key]["unit"]}
    expect_error(d, f"{section}.{key}", str(value), "physical range")


def test_wrong_shape():
    d = conti_dict()
    d["table"]["residual"]["dA_vv"]["value"] = [[1.0, 0.0], [0.0, 1.0]]
    expect_error(d, "table.residual.dA_vv", "shape 3x3")
    d = conti_dict()
    d["aero"]["magnus"]["s"]["value"] = [0.1, 0.2]
    expect_error(d, "aero.magnus.s", "6 entries")


def test_units_are_checked_and_converted():
    d = conti_dict()
    d["ball"]["radius"] = {"value": 20.0, "unit": "mm"}
    assert float(model_from_dict(d).ball.radius) == pytest.approx(0.02)
    d["ball"]["radius"] = {"value": 20.0, "unit": "furlong"}
    expect_error(d, "ball.radius", "furlong")


def test_unknown_model_and_bad_toml(tmp_path):
    with pytest.raises(ConfigError, match="bundled models"):
        load_model("nakashima2012")
    bad = tmp_path / "bad.toml"
    bad.write_text("[ball\nradius = 1")
    with pytest.raises(ConfigError, match="bad.toml.*not valid TOML"):
        load_model(bad)


def test_unknown_coefficient_family():
    d = conti_dict()
    d["aero"]["drag"]["kind"] = "spline"
    expect_error(d, "aero.drag.kind", "spline")
