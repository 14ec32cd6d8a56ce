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


def expect_plain_error(data, *fragments):
    """Like expect_error, and the message shows values as plain Python numbers."""
    with pytest.raises(ConfigError) as info:
        model_from_dict(data, "my_model.toml")
    msg = str(info.value)
    for frag in ("my_model.toml",) + fragments:
        assert frag in msg, msg
    assert "np." not in msg and "array(" not in msg, msg


@pytest.mark.parametrize("section,key,value,fragment", [
    ("table", "mu", True, "got bool"),  # numpy would read true as 1.0
    ("table", "mu", "0.25", "got str"),  # and "0.25" as 0.25
    ("ball", "radius", {"value": False, "unit": "m"}, "got bool"),
    ("ball", "radius", {"value": 0.02, "unit": 20}, "unit must be a string"),
    ("ball", "radius", {"value": 0.02}, "exactly 'value' and 'unit'"),
    ("aero", "drag", 0.55, "expected a table"),
])
def test_booleans_strings_and_missing_units_are_refused(section, key, value, fragment):
    d = conti_dict()
    d[section][key] = value
    expect_plain_error(d, f"{section}.{key}", fragment)


def test_dimensional_values_need_a_unit_dimensionless_ones_do_not():
    d = conti_dict()
    d["ball"]["radius"] = 0.02  # a bare number was taken as metres, silently
    expect_plain_error(d, "ball.radius", "0.02", 'unit = "m"')
    d = conti_dict()
    d["table"]["e1"] = 0.02
    expect_plain_error(d, "table.e1", 'unit = "s/m"')
    d = conti_dict()
    d["table"]["mu"] = 0.3
    assert float(model_from_dict(d).table.mu) == pytest.approx(0.3)


def test_a_string_inside_a_matrix_names_its_row_and_entry():
    d = conti_dict()
    d["aero"]["drag"]["cd"]["value"][2][3] = "0.41"
    expect_plain_error(d, "aero.drag.cd", "'0.41'", "row 3, entry 4")


@pytest.mark.parametrize("path,row", [(("aero", "drag", "sp"), 1), (("table", "residual", "dA_ww"), 2)])
def test_ragged_rows_name_the_key_and_the_row(path, row):
    d = conti_dict()
    table = d
    for part in path:
        table = table[part]
    table["value"][row].pop()
    n = len(table["value"][0])
    expect_plain_error(d, ".".join(path), f"row {row + 1} has {n - 1} entries but row 1 has {n}")


def _set(d, path, value):
    for part in path[:-1]:
        d = d[part]
    d[path[-1]] = value


@pytest.mark.parametrize("path,value,fragments", [
    (("table", "e_min"), {"value": 1.1, "unit": "1"}, ("table.e_min", "1.1", "outside the physical range [0.0, 1.0]")),
    (("aero", "drag", "re_ref", "value"), [6640, 33201, 19920, 46481],
     ("aero.drag.re_ref", "entry 3 (19920.0) does not exceed entry 2 (33201.0)")),
    (("aero", "drag", "re_ref", "value"), [6640], ("aero.drag.re_ref", "at least 2")),
    (("aero", "drag", "re_cap", "value"), 40000, ("aero.drag.re_cap", "46481.0")),
    (("aero", "drag", "cd_min", "value"), 0.4, ("aero.drag.cd_min", "0.37")),
    (("aero", "drag", "sp", "value"), [[0.0, 0.4, 1.0]] * 3, ("aero.drag.sp", "3 rows", "re_ref has 4")),
    (("aero", "drag", "cd", "value"), [[0.5] * 5] * 4, ("aero.drag.cd", "4x5", "4x6")),
    (("aero", "magnus", "v_ref", "value"), [2.0, 3.5, 7.5, 7.5, 13.5, 17.0], ("aero.magnus.v_ref", "entry 4")),
    (("aero", "magnus", "w_b", "value"), [0, 200, 350, 440, 550, 650], ("aero.magnus.w_b", "entry 1", "positive")),
    (("table", "geometry", "width"), {"value": 3.0, "unit": "m"}, ("table.geometry.width", "table.geometry.length = 2.74")),
    (("schema",), True, ("'schema' = True",)),
    (("name",), 7, ("'name' = 7", "string")),
])
def test_inconsistent_values_are_refused(path, value, fragments):
    d = conti_dict()
    _set(d, path, value)
    expect_plain_error(d, *fragments)


def test_a_restitution_clip_range_that_is_empty_is_refused():
    d = conti_dict()
    d["table"]["e_min"]["value"], d["table"]["e_max"]["value"] = 0.9, 0.8
    expect_plain_error(d, "table.e_min", "0.9", "exceeds table.e_max = 0.8")


def test_unsorted_breakpoints_of_one_row_name_that_row():
    d = conti_dict()
    d["aero"]["drag"]["sp"]["value"][2][2] = 0.3
    expect_plain_error(d, "aero.drag.sp", "row 3", "entry 3 (0.3) does not exceed entry 2 (0.4)")


@pytest.mark.parametrize("content", [b"schema = 1\nname = \"x\xff\xfe\"\n", bytes(range(256))])
def test_binary_or_non_utf8_model_file_names_the_file(tmp_path, content):
    f = tmp_path / "binary.toml"
    f.write_bytes(content)
    with pytest.raises(ConfigError) as info:
        load_model(f)
    assert str(f) in str(info.value) and "line" in str(info.value)
