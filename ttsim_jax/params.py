"""Model parameter pytrees and their TOML files.

A :class:`Model` gathers one parameter pytree per stage (ball, flight, table, racket), the
optional racket residual network and a tuple of effects. Every numeric leaf is an array, so models
can be batched along a leading axis (domain randomisation, see :func:`stack_models`) and
``jax.grad`` reaches every parameter. Structural choices (coefficient model families, racket model
kind, network architecture, which effects) are part of the pytree structure: changing them
recompiles, changing values does not.

TOML layout (see ``configs/models/*.toml``): every dimensional number is an inline table
``{ value = ..., unit = "..." }`` (a bare number would leave its unit to guesswork); dimensionless
ones (unit ``"1"``) may also be bare numbers. A few alternative units are converted (mm, cm, g).
Loading validates names, types, shapes, units, physical ranges and the consistency of related keys
(e_min <= e_max, increasing breakpoints, ...) and raises :class:`ConfigError` naming the file, the
key and the value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ttsim_jax.bundled import config_dir  # noqa: F401 (the public name stays here)
from ttsim_jax.errors import ConfigError
from ttsim_jax.files.toml import read_toml
from ttsim_jax.physics.aero import (
    AeroParams,
    BlendedDragTable,
    ConstantCoefficient,
    DragTable,
    DurrMagnus,
    MagnusTable,
    MagnusValueTable,
)
from ttsim_jax.physics.dimensions import FLOOR_Z, NET_HEIGHT, NET_OVERHANG, TABLE_LENGTH, TABLE_WIDTH
from ttsim_jax.physics.racket import RACKET_KINDS, RacketParams
from ttsim_jax.physics.table import TableParams

SCHEMA_VERSION = 1


@struct.dataclass
class BallParams:
    """Attributes: radius [m], mass [kg]."""

    radius: jnp.ndarray
    mass: jnp.ndarray


@struct.dataclass
class Model:
    """All parameters of one simulator model.

    Attributes:
        ball: :class:`BallParams`.
        aero: :class:`~ttsim_jax.physics.aero.AeroParams`.
        table: :class:`~ttsim_jax.physics.table.TableParams`.
        racket: :class:`~ttsim_jax.physics.racket.RacketParams`.
        residual: the racket residual network (a ``ResidualModel``) or None.
        effects: tuple of effects acting at the stages' hook points (see ``physics/hooks.py``).
        name: the model's name (static).
    """

    ball: BallParams
    aero: AeroParams
    table: TableParams
    racket: RacketParams
    residual: Any = None
    effects: tuple = ()
    name: str = struct.field(pytree_node=False, default="")


# --------------------------------------------------------------------------- schema
@dataclass(frozen=True)
class Entry:
    unit: str
    shape: tuple = ()
    lo: float = -math.inf
    hi: float = math.inf
    default: Any = None  # None: required


_R = dict(lo=0.0, hi=1.0)  # restitution-like coefficients: above 1 a bounce would gain energy
_POS = dict(lo=0.0, hi=math.inf)

SCHEMA: dict[str, dict[str, Entry]] = {
    "ball": {"radius": Entry("m", lo=1e-4, hi=0.1), "mass": Entry("kg", lo=1e-5, hi=0.1)},
    "aero": {
        "rho_air": Entry("kg/m^3", lo=1e-3, hi=10.0),
        "nu": Entry("m^2/s", lo=1e-7, hi=1e-3),
        "gravity": Entry("m/s^2", lo=0.0, hi=100.0),
        "buoyancy": Entry("bool", default=True),
    },
    "aero.drag:constant": {"value": Entry("1", **_POS)},
    "aero.drag:table": {
        "re_ref": Entry("1", (-1,), **_POS), "sp": Entry("1", (-1, -1), **_POS), "cd": Entry("1", (-1, -1), **_POS),
        "re_cap": Entry("1", **_POS), "cd_min": Entry("1", lo=0.0, hi=2.0, default=0.1),
    },
    "aero.magnus:constant": {"value": Entry("1", **_POS)},
    "aero.magnus:durr": {"gain": Entry("1", **_POS), "offset": Entry("1"), "cap": Entry("1", **_POS)},
    "aero.magnus:table": {
        "v_ref": Entry("m/s", (-1,), **_POS), "m1": Entry("s/rad", (-1,)), "s": Entry("1", (-1,)),
        "w_b": Entry("rad/s", (-1,), **_POS), "a": Entry("s^2/rad^2", (-1,)), "b": Entry("s/rad", (-1,)),
        "c": Entry("1", (-1,)),
    },
    "table": {
        "e0": Entry("1", **_R), "e1": Entry("s/m", lo=-1.0, hi=1.0), "e_min": Entry("1", **_R, default=0.0),
        "e_max": Entry("1", **_R, default=1.0), "mu": Entry("1", lo=0.0, hi=2.0), "kappa": Entry("1", lo=0.1, hi=10.0),
        "alpha_roll": Entry("1", lo=0.0, hi=1.0, default=0.4),
    },
    "table.residual": {
        "dA_vv": Entry("1", (3, 3), default=0.0), "dA_vw": Entry("m", (3, 3), default=0.0),
        "dA_wv": Entry("1/m", (3, 3), default=0.0), "dA_ww": Entry("1", (3, 3), default=0.0),
    },
    "table.geometry": {
        "length": Entry("m", **_POS, default=TABLE_LENGTH), "width": Entry("m", **_POS, default=TABLE_WIDTH),
        "net_height": Entry("m", **_POS, default=NET_HEIGHT), "net_overhang": Entry("m", **_POS, default=NET_OVERHANG),
        "floor_z": Entry("m", hi=0.0, default=FLOOR_Z),
    },
    "racket": {
        "kind": Entry("str"),
        "e0": Entry("1", **_R), "e1": Entry("s/m", lo=-1.0, hi=1.0, default=0.0),
        "et0": Entry("1", **_R, default=0.0), "et1": Entry("s/m", lo=-1.0, hi=1.0, default=0.0),
        "e_s": Entry("1", **_R, default=1.0), "k_p": Entry("kg", **_POS, default=0.0),
        "kappa": Entry("1", lo=0.1, hi=10.0), "e_max": Entry("1", **_R, default=1.0),
    },
}

SCHEMA["aero.drag:table_blended"] = SCHEMA["aero.drag:table"]
SCHEMA["aero.magnus:table_values"] = SCHEMA["aero.magnus:table"]
# A model file's ``kind`` of each coefficient model -> its class. Two readings of the paper's tables
# (see docs/physics.md, "Open readings"): "table" is the default, the other a named variant.
DRAG_KINDS = {"constant": ConstantCoefficient, "table": DragTable, "table_blended": BlendedDragTable}
MAGNUS_KINDS = {"constant": ConstantCoefficient, "durr": DurrMagnus, "table": MagnusTable,
                "table_values": MagnusValueTable}

_CONVERT = {"mm": ("m", 1e-3), "cm": ("m", 1e-2), "g": ("kg", 1e-3), "mm^2/s": ("m^2/s", 1e-6)}
_SECTIONS = {"ball", "aero", "table", "racket", "schema", "name", "description", "source", "extends"}


def _error(file, key, value, why):
    # numpy values would print as np.float64(...); users want the numbers as written in the file.
    if isinstance(value, (np.ndarray, np.generic)):
        value = value.tolist()
    raise ConfigError(f"{file}: key '{key}' = {value!r}: {why}")


def _position(index: tuple) -> str:
    """1-based position in a nested TOML array, as a user counts: 'entry 3', 'row 2, entry 5'."""
    if len(index) == 1:
        return f"entry {index[0] + 1}"
    if len(index) == 2:
        return f"row {index[0] + 1}, entry {index[1] + 1}"
    return "element " + "".join(f"[{i + 1}]" for i in index)


def _size(shape: tuple) -> str:
    if not shape:
        return "a single number"
    return f"{shape[0]} entries" if len(shape) == 1 else "shape " + "x".join(map(str, shape))


def _to_array(file, key, raw, unit):
    """A number or rectangular nested list of numbers -> float64 array.

    Booleans and strings are refused (numpy would turn true into 1.0 and "2" into 2.0), and a
    ragged nested list names its first row whose length differs.
    """

    def shape(x, index):
        if isinstance(x, list):
            shapes = [shape(item, index + (i,)) for i, item in enumerate(x)]
            for i, sh in enumerate(shapes[1:], start=1):
                if sh != shapes[0]:
                    what = "row" if not index else f"{_position(index)}: row"
                    _error(file, key, x[i], f"ragged: {what} {i + 1} has {_size(sh)} but {what} 1 has "
                           f"{_size(shapes[0])}; every row needs the same length")
            return (len(x),) + (shapes[0] if shapes else ())
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            where = f" ({_position(index)})" if index else ""
            in_unit = "(dimensionless)" if unit == "1" else f"in {unit}"
            _error(file, key, x, f"expected a number{where} {in_unit}, got {type(x).__name__}")
        return ()

    shape(raw, ())
    return np.asarray(raw, dtype=np.float64)


def _read_entry(file, key, raw, entry: Entry):
    if entry.unit == "str":
        if not isinstance(raw, str):
            _error(file, key, raw, "expected a string")
        return raw
    if entry.unit == "bool":
        if not isinstance(raw, bool):
            _error(file, key, raw, "expected true or false")
        return raw
    unit = entry.unit
    inline = isinstance(raw, dict)
    if inline:
        if set(raw) != {"value", "unit"}:
            _error(file, key, raw, "an inline table needs exactly 'value' and 'unit'")
        unit = raw["unit"]
        if not isinstance(unit, str):
            _error(file, key, unit, f"the unit must be a string such as \"{entry.unit}\"")
        raw = raw["value"]
    arr = _to_array(file, key, raw, entry.unit)
    if not inline and entry.unit != "1":
        _error(file, key, raw, f"a dimensional value needs its unit: write {{ value = ..., unit = \"{entry.unit}\" }}")
    if unit != entry.unit:
        target, factor = _CONVERT.get(unit, (None, None))
        if target != entry.unit:
            _error(file, key, raw, f"unit '{unit}' is not '{entry.unit}' nor convertible to it")
        arr = arr * factor
    if len(entry.shape) != arr.ndim or any(s not in (-1, a) for s, a in zip(entry.shape, arr.shape)):
        want = "scalar" if not entry.shape else "x".join("N" if s == -1 else str(s) for s in entry.shape)
        _error(file, key, raw, f"expected shape {want}, got {arr.shape or 'scalar'}")
    if not np.all(np.isfinite(arr)):
        _error(file, key, raw, "must be finite")
    if np.any(arr < entry.lo) or np.any(arr > entry.hi):
        _error(file, key, raw, f"outside the physical range [{entry.lo}, {entry.hi}] {entry.unit}")
    return arr


def _read_section(file, data: dict, section: str, schema_key: str | None = None, skip=()):
    schema = SCHEMA[schema_key or section]
    table = data
    for part in section.split("."):
        table = table.get(part, {}) if isinstance(table, dict) else {}
    if not isinstance(table, dict):
        _error(file, section, table, "expected a table")
    unknown = set(table) - set(schema) - set(skip)
    if unknown:
        k = sorted(unknown)[0]
        _error(file, f"{section}.{k}", table[k], f"unknown key; known keys of [{section}]: {sorted(schema)}")
    out = {}
    for key, entry in schema.items():
        if key in table:
            out[key] = _read_entry(file, f"{section}.{key}", table[key], entry)
        elif entry.default is None:
            _error(file, f"{section}.{key}", None, f"missing (unit {entry.unit})")
        else:
            out[key] = entry.default if entry.unit in ("bool", "str") else np.broadcast_to(
                np.float64(entry.default), tuple(3 if s == -1 else s for s in entry.shape)).copy()
    return out


def _coefficient(file, data, section, families):
    table = data.get("aero", {}).get(section.split(".")[1], None)
    if table is not None and not isinstance(table, dict):
        _error(file, section, table, "expected a table with 'kind' and the coefficients")
    if table is None or "kind" not in table:
        _error(file, f"{section}.kind", None, f"missing; one of {sorted(families)}")
    kind = table["kind"]
    if not isinstance(kind, str) or kind not in families:
        _error(file, f"{section}.kind", kind, f"unknown coefficient model; one of {sorted(families)}")
    vals = _read_section(file, data, section, f"{section}:{kind}", skip=("kind",))
    return families[kind], kind, vals


def _check_increasing(file, key, values, what):
    """Refuses fewer than two values or values that do not strictly increase, naming the first."""
    if values.shape[0] < 2:
        _error(file, key, values, f"needs at least 2 {what}")
    bad = np.flatnonzero(np.diff(values) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        _error(file, key, values, f"{what} must increase: entry {i + 1} ({values[i].item()!r}) does not exceed "
               f"entry {i} ({values[i - 1].item()!r})")


def _check_tables(file, kind, vals):
    """Consistency of the tabulated coefficient models (shapes agree, breakpoints increase)."""
    if kind in ("table", "table_blended") and "sp" in vals:
        _check_increasing(file, "aero.drag.re_ref", vals["re_ref"], "reference Reynolds numbers")
        k = vals["re_ref"].shape[0]
        if vals["sp"].shape[0] != k:
            _error(file, "aero.drag.sp", vals["sp"], f"has {vals['sp'].shape[0]} rows but re_ref has {k} entries: "
                   "one row of breakpoints per reference Reynolds number")
        if vals["cd"].shape != vals["sp"].shape:
            _error(file, "aero.drag.cd", vals["cd"], f"shape {vals['cd'].shape[0]}x{vals['cd'].shape[1]} differs from "
                   f"sp's {vals['sp'].shape[0]}x{vals['sp'].shape[1]}: one C_D per breakpoint")
        for row, sp in enumerate(vals["sp"]):
            _check_increasing(file, "aero.drag.sp", sp, f"spin-ratio breakpoints of row {row + 1}")
        if vals["re_cap"] < vals["re_ref"][-1]:
            _error(file, "aero.drag.re_cap", vals["re_cap"], f"must be at least the last re_ref ({vals['re_ref'][-1].item()!r})")
        if vals["cd_min"] > vals["cd"].min():
            _error(file, "aero.drag.cd_min", vals["cd_min"], f"the lower clamp exceeds the smallest tabulated C_D "
                   f"({vals['cd'].min().item()!r}) and would override the table")
    if kind in ("table", "table_values") and "v_ref" in vals:
        _check_increasing(file, "aero.magnus.v_ref", vals["v_ref"], "reference speeds")
        k = vals["v_ref"].shape[0]
        for key in ("m1", "s", "w_b", "a", "b", "c"):
            if vals[key].shape != (k,):
                _error(file, f"aero.magnus.{key}", vals[key], f"must have {k} entries like v_ref")
        bad = np.flatnonzero(vals["w_b"] <= 0)
        if bad.size:
            _error(file, "aero.magnus.w_b", vals["w_b"], f"entry {int(bad[0]) + 1}: the spin rate where the linear "
                   "piece of C_M hands over to the quadratic one must be positive")


def _check_pairs(file, table, geometry):
    """Keys whose values must agree with each other."""
    if table["e_min"] > table["e_max"]:
        _error(file, "table.e_min", table["e_min"], f"exceeds table.e_max = {table['e_max'].item()!r}: "
               "the restitution clip range [e_min, e_max] is empty")
    if geometry["width"] > geometry["length"]:
        _error(file, "table.geometry.width", geometry["width"], f"exceeds table.geometry.length = "
               f"{geometry['length'].item()!r}: x runs along the table's length, the longer side")


def model_from_dict(data: dict, file: str = "<dict>", dtype=None) -> Model:
    """Builds and validates a :class:`Model` from a parsed TOML document."""
    unknown = set(data) - _SECTIONS
    if unknown:
        k = sorted(unknown)[0]
        _error(file, k, data[k], f"unknown top-level key; known: {sorted(_SECTIONS)}")
    for key in ("name", "description", "source"):
        if key in data and not isinstance(data[key], str):
            _error(file, key, data[key], "expected a string")
    version = data.get("schema", SCHEMA_VERSION)
    if isinstance(version, bool) or version != SCHEMA_VERSION:
        _error(file, "schema", data.get("schema"), f"this version of ttsim-jax reads schema {SCHEMA_VERSION}")
    dtype = dtype or jnp.zeros(()).dtype
    arr = lambda x: jnp.asarray(x, dtype)  # noqa: E731

    ball = _read_section(file, data, "ball")
    aero = _read_section(file, data, "aero", skip=("drag", "magnus"))
    drag_cls, drag_kind, drag = _coefficient(file, data, "aero.drag", DRAG_KINDS)
    magnus_cls, magnus_kind, magnus = _coefficient(file, data, "aero.magnus", MAGNUS_KINDS)
    _check_tables(file, drag_kind, drag)
    _check_tables(file, magnus_kind, magnus)
    table = _read_section(file, data, "table", skip=("residual", "geometry"))
    residual = _read_section(file, data, "table.residual")
    geometry = _read_section(file, data, "table.geometry")
    _check_pairs(file, table, geometry)
    racket = _read_section(file, data, "racket")
    if racket["kind"] not in RACKET_KINDS:
        _error(file, "racket.kind", racket["kind"], f"one of {RACKET_KINDS}")
    if racket["kind"] != "updated" and racket["k_p"] <= 0:
        _error(file, "racket.k_p", float(racket["k_p"]), f"the '{racket['kind']}' model needs k_p > 0")

    return Model(
        ball=BallParams(radius=arr(ball["radius"]), mass=arr(ball["mass"])),
        aero=AeroParams(
            rho_air=arr(aero["rho_air"]), nu=arr(aero["nu"]), gravity=arr([0.0, 0.0, -aero["gravity"]]),
            buoyancy=arr(1.0 if aero["buoyancy"] else 0.0),
            drag=drag_cls(**{k: arr(v) for k, v in drag.items()}),
            magnus=magnus_cls(**{k: arr(v) for k, v in magnus.items()})),
        table=TableParams(
            **{k: arr(v) for k, v in table.items()},
            residual=arr(np.stack([residual[k] for k in ("dA_vv", "dA_vw", "dA_wv", "dA_ww")])),
            **{k: arr(v) for k, v in geometry.items()}),
        racket=RacketParams(kind=racket.pop("kind"), **{k: arr(v) for k, v in racket.items()}),
        name=str(data.get("name", Path(file).stem)),
    )


def available_models() -> list[str]:
    """Names of the bundled models (``configs/models/*.toml``)."""
    return sorted(p.stem for p in (config_dir() / "models").glob("*.toml"))


def resolve_model_path(name_or_path: str | Path) -> Path:
    """The model file for a bundled model name or a path to a ``.toml`` file.

    Arguments:
        name_or_path: ``"conti2026"`` etc., or a path.

    Returns:
        The path of an existing file; raises :class:`ConfigError` naming the name or path otherwise.
    """
    model, racket = split_model_name(name_or_path)
    if racket is not None:
        raise ConfigError(f"{name_or_path!r}: a model with a racket configuration has no model file of its own; load "
                          f"it with load_model({name_or_path!r}) (here: give {model!r} and the racket apart, or use a "
                          "command that takes MODEL+RACKET)")
    return _bundled_or_path(name_or_path, "models", "model", available_models)


def split_model_name(name_or_path):
    """(model, racket) of a name ``"MODEL+RACKET"`` (``"conti2026+racket_05"``: a model with a
    racket configuration, as :func:`load_model` names it); (``name_or_path``, None) otherwise."""
    if isinstance(name_or_path, str) and "+" in name_or_path and not Path(name_or_path).exists():
        model, _, racket = name_or_path.partition("+")
        return model, racket
    return name_or_path, None


def _bundled_or_path(name_or_path, folder: str, what: str, available) -> Path:
    """The file of a bundled ``what`` (``configs/FOLDER/NAME.toml``) or the given path, checked."""
    path = Path(name_or_path)
    if path.suffix == ".toml" or path.exists():
        if path.is_dir():
            raise ConfigError(f"{path}: is a directory, not a {what} .toml file")
        if not path.is_file():
            raise ConfigError(f"{path}: no such {what} file")
        return path
    path = config_dir() / folder / f"{name_or_path}.toml"
    if not path.is_file():
        raise ConfigError(f"unknown {what} {str(name_or_path)!r}; bundled {what}s: {available()} "
                          f"(or give a path to a {what} .toml file)")
    return path


def _overlay(base: dict, over: dict) -> dict:
    """``base`` with ``over`` laid on it: tables merge key by key; a value, or an entry
    (a table with ``value``), replaces the base's whole."""
    out = dict(base)
    for key, val in over.items():
        if isinstance(val, dict) and "value" not in val and isinstance(out.get(key), dict):
            out[key] = _overlay(out[key], val)
        else:
            out[key] = val
    return out


def read_model_file(path: Path, _chain: tuple = ()) -> dict:
    """The parsed model file ``path``, with ``extends = "BASE"`` resolved.

    A variant names its base (a bundled model's name, or a path relative to the variant's folder)
    and gives only what differs; the base's ``name`` is not inherited (a variant is named after
    its file unless it says otherwise).
    """
    data = read_toml(path, "model file")
    base = data.pop("extends", None)
    if base is None:
        return data
    if not isinstance(base, str) or not base:
        _error(str(path), "extends", base, "expected the name of a bundled model or a path to a .toml file")
    base_path = Path(base)
    if base_path.suffix == ".toml" and not base_path.is_absolute():
        base_path = path.parent / base_path
    try:
        base_path = resolve_model_path(base_path if base_path.suffix == ".toml" else base)
    except ConfigError as e:
        _error(str(path), "extends", base, str(e))
    chain = _chain + (path.resolve(),)
    if base_path.resolve() in chain:
        _error(str(path), "extends", base, "the models extend each other in a cycle: "
               + " -> ".join(p.name for p in chain + (base_path.resolve(),)))
    merged = read_model_file(base_path, chain)
    merged.pop("name", None)
    return _overlay(merged, data)


def available_rackets() -> list[str]:
    """Names of the bundled racket configurations (``configs/rackets/*.toml``)."""
    return sorted(p.stem for p in (config_dir() / "rackets").glob("*.toml"))


def resolve_racket_path(name_or_path: str | Path) -> Path:
    """The racket file of a bundled racket configuration's name (``"racket_01"``) or a path to one."""
    return _bundled_or_path(name_or_path, "rackets", "racket", available_rackets)


def read_racket_file(path: Path) -> tuple[dict, Path | None]:
    """(the ``[racket]`` table, the residual network file or None) of a racket file: a fitted racket
    configuration (``configs/rackets/*.toml``, written by ``benchmarks/racket_configs_real.py``),
    whose optional ``network`` names a ``.ttres`` beside it."""
    data = read_toml(path, "racket file")
    unknown = set(data) - {"schema", "name", "description", "source", "racket", "network", "held_out"}
    if unknown:
        _error(str(path), sorted(unknown)[0], data[sorted(unknown)[0]], "unknown key; known: schema, name, description, "
               "source, racket, network, held_out")
    if not isinstance(data.get("racket"), dict):
        _error(str(path), "racket", data.get("racket"), "expected a [racket] table")
    net = data.get("network")
    if net is None:
        return data["racket"], None
    net_path = path.parent / str(net)
    if not net_path.is_file():
        _error(str(path), "network", net, f"no such file {net_path}")
    return data["racket"], net_path


def load_model(name_or_path: str | Path, dtype=None, residual=None, effects: tuple = (), racket=None,
               racket_network: bool = True) -> Model:
    """Loads a model by bundled name (``"conti2026"``) or TOML path.

    Arguments:
        name_or_path: bundled model name or path to a ``.toml`` file.
        dtype: float dtype of the parameters (default: JAX's default float).
        residual: optional racket residual network (``ResidualModel``) or a path to its checkpoint.
        effects: tuple of effects to attach.
        racket: optional racket configuration, a bundled name (:func:`available_rackets`, e.g.
            ``"racket_01"``: tt_rackets' offensive blade with inverted rubber) or a racket file:
            its fitted ``[racket]`` parameters replace the model's, and its residual network, where
            it has one, becomes the model's (unless ``residual`` is given). The model is named
            ``MODEL+RACKET``, and that name loads it too (``load_model("conti2026+racket_05")``, or
            ``--model conti2026+racket_05`` on the command line).
        racket_network: with ``racket``, attach the configuration's residual network (False: the
            fitted base model alone).

    Returns:
        A validated :class:`Model`.
    """
    from ttsim_jax.files.cache import enable_compilation_cache

    enable_compilation_cache()  # a library user's first step: later processes load what this one compiles
    name_or_path, named = split_model_name(name_or_path)
    racket = named if racket is None else racket
    path = _bundled_or_path(name_or_path, "models", "model", available_models)
    doc = read_model_file(path)
    if racket is not None:
        racket_path = resolve_racket_path(racket)
        table, net = read_racket_file(racket_path)
        doc = dict(doc, racket=table, name=f"{doc.get('name', path.stem)}+{racket_path.stem}")
        if residual is None and racket_network and net is not None:
            residual = net
    model = model_from_dict(doc, str(path), dtype)
    if isinstance(residual, (str, Path)):
        from ttsim_jax.physics.network_checkpoint import load_residual
        residual = load_residual(residual)
    return model.replace(residual=residual, effects=tuple(effects))


def stack_models(models) -> Model:
    """Stacks models of identical structure along a new leading axis (for batched simulation)."""
    return jax.tree.map(lambda *xs: jnp.stack(xs), *models)
