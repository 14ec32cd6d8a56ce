"""Per-segment aerodynamic coefficients -> the paper's functional forms -> a model config.

The per-segment fits of :mod:`ttsim_jax.fit.flightfit` give one constant (C_D, C_M) per segment, each
associated with the segment's effective speed (drag: sum |v|^3 / sum |v|^2; Magnus: the
sin-weighted one) and its spin rate. This module regresses them into the paper's forms:

* C_D(Re, Sp) (:class:`~ttsim_jax.physics.aero.DragTable`): the Sp breakpoints of each reference
  Reynolds number are kept from a base model; the table's C_D values are fitted. The table is
  linear in its C_D values (interpolation in Sp along each reference curve, then in Re), so the
  regression is a weighted linear least-squares problem whose design matrix is the Jacobian of
  :func:`~ttsim_jax.physics.aero.drag_table` itself with respect to those values.
* C_M(v, w) (:class:`~ttsim_jax.physics.aero.MagnusTable`): reference speeds v_ref and the
  hand-over spin rates w_b are kept; m1, s (linear piece) and a, b, c (quadratic piece) of each
  reference speed are fitted, with the coefficients interpolated linearly in v as the model does,
  and a soft constraint that the two pieces meet at w_b.

Which speed a segment's coefficient belongs to (``association``):

* ``"v_eff"`` (the paper): the coefficient is the form evaluated at the effective speed, the mean
  of the speeds |v_i| along the fitted trajectory weighted by the force's size (drag: |v_i|^2;
  Magnus: |v_i| sin(theta_i)), which gives the paper's two v_eff formulas;
* ``"averaged"``: the coefficient is the same weighted mean of the *form* over the samples. The
  form is still linear in the fitted values, and a segment whose speed and spin ratio sweep across
  a ridge or a trough of C_D(Sp) is no longer credited with the value at one mean point.

Both are ridge-regularised towards the base model's values (``prior`` pseudo-observations per
entry), so entries without data stay at the base model; :class:`FormFit` reports each entry's
support (the summed interpolation weight of the segments that inform it) so that "where data
exists" is explicit. Segment weights are 1 / (stderr^2 + floor^2).

:func:`export_config` writes a model TOML: the base model's file with its ``[aero.drag]`` and
``[aero.magnus]`` sections replaced (by :func:`write_config`, which the contact stages use too);
``load_model`` reads it.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.fit.choices import ASSOCIATIONS
from ttsim_jax.physics import aero as aero_stage

#: Spin-rate scale of the Magnus regression's unknowns [rad/s] (keeps the columns comparable).
W_SCALE = 100.0


@dataclasses.dataclass
class FormFit:
    """A regressed coefficient table.

    Attributes:
        values: name -> fitted array (drag: ``cd`` (K, P); Magnus: ``m1, s, a, b, c`` (K,)).
        prior: the base model's values, same layout.
        support: per-entry summed interpolation weight of the segments used ((K, P) or (K,)).
        n_used: segments used; rms_residual: weighted RMS of (segment coefficient - form) over them.
    """

    values: dict
    prior: dict
    support: np.ndarray
    n_used: int
    rms_residual: float


def _weights(stderr, floor):
    return 1.0 / (np.asarray(stderr, np.float64) ** 2 + floor**2)


def _ridge(a, y, w, prior, alpha, extra_a=None, extra_y=None):
    """argmin_x sum w (a x - y)^2 + alpha_eff |x - prior|^2 (+ extra rows); alpha_eff = alpha * median(w)."""
    sw = np.sqrt(w)[:, None]
    rows, rhs = [a * sw], [y * sw[:, 0]]
    lam = np.sqrt(alpha * (np.median(w) if len(w) else 1.0))
    rows.append(lam * np.eye(a.shape[1]))
    rhs.append(lam * prior)
    if extra_a is not None:
        rows.append(extra_a)
        rhs.append(extra_y)
    x, *_ = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)
    return x




def force_weights(velocities, spin, kind: str):
    """Per segment, the speeds along the fitted trajectory and the weights of the force's size.

    Arguments:
        velocities: list of (T_i, 3) fitted velocities [m/s] (``SegmentFits.velocities``).
        spin: (S, 3) spins [rad/s].
        kind: ``"drag"`` (weights |v|^2) or ``"magnus"`` (weights |v| sin(theta)).

    Returns:
        list of (speeds (T_i,), weights (T_i,) summing to 1). The weighted mean speed is the
        paper's v_eff.
    """
    out = []
    for vel, w in zip(velocities, np.asarray(spin, np.float64)):
        vel = np.asarray(vel, np.float64)
        speed = np.linalg.norm(vel, axis=1)
        if kind == "drag":
            weight = speed**2
        elif kind == "magnus":
            weight = np.linalg.norm(np.cross(vel, w), axis=1) / max(np.linalg.norm(w), 1e-9)
        else:
            raise ValueError(f"kind must be 'drag' or 'magnus', not {kind!r}")
        total = weight.sum()
        out.append((speed, weight / total if total > 0 else np.full(len(speed), 1.0 / len(speed))))
    return out


def _points(samples, association: str):
    """Flattened (speeds, weights) and the segment of each point, for the chosen association."""
    if association not in ASSOCIATIONS:
        raise ValueError(f"association must be one of {ASSOCIATIONS}, not {association!r}")
    if association == "v_eff":
        samples = [(np.array([np.sum(sp * wt)]), np.ones(1)) for sp, wt in samples]
    seg = np.concatenate([np.full(len(sp), j) for j, (sp, _) in enumerate(samples)]).astype(int)
    speeds = np.concatenate([sp for sp, _ in samples])
    weights = np.concatenate([wt for _, wt in samples])
    return speeds, weights, seg


def _segment_sum(rows, weights, seg, n):
    out = np.zeros((n, rows.shape[1]))
    np.add.at(out, seg, rows * weights[:, None])
    return out


def _chunked(fn, *arrays, chunk: int = 4096) -> np.ndarray:
    """fn over the points of 1-D ``arrays`` in padded chunks of one size (one compilation for any count)."""
    n = len(arrays[0])
    out = []
    for start in range(0, max(n, 1), chunk):
        part = [np.asarray(a[start:start + chunk], np.float32) for a in arrays]
        k = len(part[0])
        part = [np.pad(a, (0, chunk - k), mode="edge") if k else np.ones(chunk, np.float32) for a in part]
        out.append(np.asarray(fn(*part), np.float64)[:k])
    return np.concatenate(out)


@jax.jit
def _drag_rows(cd, re_ref, sp, re_cap, radius, nu, speed, spin_rate):
    def cd_at(cd, v, w):
        # No lower clamp: the table is then exactly linear in its C_D values.
        t = aero_stage.DragTable(re_ref, sp, cd, re_cap, jnp.asarray(-jnp.inf, cd.dtype))
        return aero_stage.drag_table(t, v, w, radius, nu)

    return jax.vmap(jax.jacfwd(cd_at), in_axes=(None, 0, 0))(cd, speed, spin_rate)


def drag_design(table: aero_stage.DragTable, speed, spin_rate, radius, nu) -> np.ndarray:
    """(N, K*P) matrix W with C_D(speed_j, spin_j) = W_j . cd.ravel() for the table's breakpoints."""
    arr = lambda x: jnp.asarray(np.asarray(x, np.float64), jnp.float32)  # noqa: E731
    fixed = (arr(table.re_ref), arr(table.sp), arr(table.re_cap), arr(radius), arr(nu))
    jac = _chunked(lambda v, w: _drag_rows(arr(table.cd), *fixed, v, w), speed, spin_rate)
    return jac.reshape(len(speed), -1)


def fit_drag_table(base: aero_stage.DragTable, cd, stderr, samples, spin_rate, radius, nu, *,
                   association: str = "v_eff", alpha: float = 1.0, floor: float = 0.01) -> FormFit:
    """Regresses per-segment C_D into the table of ``base`` (its breakpoints kept).

    Arguments:
        base: the base model's :class:`~ttsim_jax.physics.aero.DragTable` (prior and breakpoints).
        cd, stderr: (S,) fitted C_D and its standard error.
        samples: :func:`force_weights` of the segments (kind ``"drag"``).
        spin_rate: (S,) |w| [rad/s].
        radius, nu: ball radius [m], kinematic viscosity [m^2/s].
        association: ``"v_eff"`` (the paper) or ``"averaged"`` (see the module docstring).
        alpha: prior strength, in pseudo-observations of median weight per entry.
        floor: added in quadrature to the standard errors [1] (no segment dominates).

    Returns:
        :class:`FormFit` with ``values["cd"]`` (K, P).
    """
    prior = np.asarray(base.cd, np.float64)
    speeds, weights, seg = _points(samples, association)
    rows = drag_design(base, speeds, np.asarray(spin_rate, np.float64)[seg], radius, nu)
    a = _segment_sum(rows, weights, seg, len(cd))
    w = _weights(stderr, floor)
    x = _ridge(a, np.asarray(cd, np.float64), w, prior.ravel(), alpha)
    resid = a @ x - cd
    return FormFit(values={"cd": x.reshape(prior.shape)}, prior={"cd": prior},
                   support=a.sum(0).reshape(prior.shape), n_used=len(cd),
                   rms_residual=float(np.sqrt(np.sum(w * resid**2) / max(np.sum(w), 1e-30))))


MAGNUS_FITTED = ("m1", "s", "a", "b", "c")


def _speed_weights(v_ref, speed) -> np.ndarray:
    """(N, K) weights of the reference speeds in the model's linear interpolation of its coefficients."""
    return _chunked(lambda v: _interpolation_weights(v, jnp.asarray(v_ref, jnp.float32)), speed)


@jax.jit
def _interpolation_weights(x, xp):
    eye = jnp.eye(xp.shape[0], dtype=xp.dtype)
    return jax.vmap(lambda v: aero_stage._piecewise(v, xp, eye))(x)


def _magnus_rows(lam, wb, w):
    """Design rows over the scaled unknowns [m1', s, a', b', c] per reference speed (N, 5K)."""
    ws = w / W_SCALE
    linear = (w <= lam @ wb)[:, None]
    cols = [lam * ws[:, None] * linear, lam * linear, lam * (ws**2)[:, None] * ~linear,
            lam * ws[:, None] * ~linear, lam * ~linear]
    return np.concatenate(cols, axis=1)


def _scale_magnus(values: dict, inverse: bool = False) -> dict:
    """Physical m1, a, b <-> the regression's W_SCALE-scaled unknowns."""
    f = {"m1": W_SCALE, "s": 1.0, "a": W_SCALE**2, "b": W_SCALE, "c": 1.0}
    return {k: np.asarray(values[k], np.float64) / f[k] if inverse else np.asarray(values[k], np.float64) * f[k]
            for k in MAGNUS_FITTED}


def fit_magnus_table(base: aero_stage.MagnusTable, cm, stderr, samples, spin_rate, *, association: str = "v_eff",
                     alpha: float = 1.0, floor: float = 0.01, continuity: float = 10.0) -> FormFit:
    """Regresses per-segment C_M into the piecewise form of ``base`` (its v_ref and w_b kept).

    Arguments:
        base: the base model's :class:`~ttsim_jax.physics.aero.MagnusTable`.
        cm, stderr: (S,) fitted C_M and its standard error.
        samples: :func:`force_weights` of the segments (kind ``"magnus"``).
        spin_rate: (S,) |w| [rad/s].
        association, alpha, floor: as in :func:`fit_drag_table`.
        continuity: weight (in pseudo-observations of median weight) of the rows asking the linear
            and quadratic pieces of each reference speed to meet at its w_b.

    Returns:
        :class:`FormFit` with ``values`` m1, s, a, b, c (K,) in the config's units.
    """
    v_ref = np.asarray(base.v_ref, np.float64)
    wb = np.asarray(base.w_b, np.float64)
    k = len(v_ref)
    prior = {key: np.asarray(getattr(base, key), np.float64) for key in MAGNUS_FITTED}
    scaled_prior = _scale_magnus(prior)
    speeds, weights, seg = _points(samples, association)
    lam = _speed_weights(v_ref, speeds)
    rows = _magnus_rows(lam, wb, np.asarray(spin_rate, np.float64)[seg])
    a = _segment_sum(rows, weights, seg, len(cm))
    w = _weights(stderr, floor)
    # Continuity at w_b of each reference speed: m1' wb' + s - (a' wb'^2 + b' wb' + c) = 0.
    wbs = wb / W_SCALE
    cont = np.zeros((k, 5 * k))
    for i in range(k):
        cont[i, [i, k + i, 2 * k + i, 3 * k + i, 4 * k + i]] = [wbs[i], 1.0, -wbs[i] ** 2, -wbs[i], -1.0]
    beta = np.sqrt(continuity * (np.median(w) if len(w) else 1.0))
    x = _ridge(a, np.asarray(cm, np.float64), w, np.concatenate([scaled_prior[key] for key in MAGNUS_FITTED]),
               alpha, beta * cont, np.zeros(k))
    values = _scale_magnus({key: x[i * k:(i + 1) * k] for i, key in enumerate(MAGNUS_FITTED)}, inverse=True)
    resid = a @ x - cm
    return FormFit(values=values, prior=prior, support=_segment_sum(lam, weights, seg, len(cm)).sum(0),
                   n_used=len(cm), rms_residual=float(np.sqrt(np.sum(w * resid**2) / max(np.sum(w), 1e-30))))


# --------------------------------------------------------------------------- config export
def toml_array(a) -> str:
    a = np.asarray(a, np.float64)
    if a.ndim == 1:
        return "[" + ", ".join(f"{x:.6g}" for x in a) + "]"
    return "[\n" + "".join(f"    {toml_array(row)},\n" for row in a) + "]"


def drag_section(base: aero_stage.DragTable, cd) -> str:
    """The ``[aero.drag]`` TOML section of a drag table with the base's breakpoints and C_D ``cd``."""
    cd_min = min(float(base.cd_min), float(np.min(cd)))
    return ("[aero.drag]                                     # fitted: C_D(Re, Sp) breakpoint table\n"
            'kind = "table"\n'
            f're_ref = {{ value = {toml_array(base.re_ref)}, unit = "1" }}\n'
            f'sp = {{ value = {toml_array(base.sp)}, unit = "1" }}\n'
            f'cd = {{ value = {toml_array(cd)}, unit = "1" }}\n'
            f're_cap = {{ value = {float(base.re_cap):.6g}, unit = "1" }}\n'
            f'cd_min = {{ value = {cd_min:.6g}, unit = "1" }}\n')


def magnus_section(base: aero_stage.MagnusTable, values: dict) -> str:
    """The ``[aero.magnus]`` TOML section with the base's v_ref, w_b and the fitted coefficients."""
    units = {"m1": "s/rad", "s": "1", "a": "s^2/rad^2", "b": "s/rad", "c": "1"}
    lines = ["[aero.magnus]                                   # fitted: C_M(v, w) per reference speed",
             'kind = "table"',
             f'v_ref = {{ value = {toml_array(base.v_ref)}, unit = "m/s" }}',
             f'w_b = {{ value = {toml_array(base.w_b)}, unit = "rad/s" }}']
    lines += [f'{k} = {{ value = {toml_array(values[k])}, unit = "{units[k]}" }}' for k in MAGNUS_FITTED]
    return "\n".join(lines) + "\n"


def replace_sections(text: str, sections: dict[str, str]) -> str:
    """TOML ``text`` with each ``[name]`` section (up to the next header) replaced by its new text.

    Raises:
        KeyError: a section is not in ``text``.
    """
    for name, body in sections.items():
        head = re.search(rf"^\[{re.escape(name)}\][^\n]*\n", text, flags=re.M)
        if head is None:
            raise KeyError(f"no [{name}] section")
        nxt = re.search(r"^\[", text[head.end():], flags=re.M)
        end = head.end() + nxt.start() if nxt else len(text)
        text = text[:head.start()] + body + "\n" + text[end:]
    return text


def export_config(base_path, out_path, drag_cd, magnus_values: dict, *, name: str, source: str) -> Path:
    """Writes a model TOML: ``base_path``'s file with fitted ``[aero.drag]`` and ``[aero.magnus]``.

    Arguments:
        base_path: the base model's TOML (needs table-kind drag and Magnus sections).
        out_path: file to write.
        drag_cd: (K, P) fitted C_D; magnus_values: fitted m1, s, a, b, c (K,).
        name, source: the new model's ``name`` and ``source`` strings.

    Returns:
        The written path (checked by loading it with :func:`ttsim_jax.params.load_model`).
    """
    return write_config(base_path, out_path, aero_sections(base_path, drag_cd, magnus_values), name=name,
                        source=source)


def aero_sections(base_path, drag_cd, magnus_values: dict) -> dict:
    """{section name: TOML text} of fitted ``[aero.drag]`` and ``[aero.magnus]`` over a base model."""
    from ttsim_jax.params import load_model

    base = load_model(Path(base_path))
    return {"aero.drag": drag_section(base.aero.drag, drag_cd),
            "aero.magnus": magnus_section(base.aero.magnus, magnus_values)}


def config_text(base_path, sections: dict, *, name: str, source: str) -> str:
    """A model TOML's text: ``base_path``'s file with some sections replaced.

    Arguments:
        base_path: the base model's TOML.
        sections: section name (e.g. ``"table.residual"``) -> its new TOML text (header included).
        name, source: the new model's ``name`` and ``source`` strings.

    Returns:
        The text.
    """
    text = replace_sections(Path(base_path).read_text(encoding="utf-8"), sections)
    text = re.sub(r'^name = .*$', f"name = {_toml_string(name)}", text, count=1, flags=re.M)
    return re.sub(r'^source = .*$', f"source = {_toml_string(source)}", text, count=1, flags=re.M)


def write_config(base_path, out_path, sections: dict, *, name: str, source: str) -> Path:
    """Writes a model TOML: ``base_path``'s file with some sections replaced (:func:`config_text`).

    Arguments:
        base_path: the base model's TOML.
        out_path: file to write.
        sections: section name (e.g. ``"table.residual"``) -> its new TOML text (header included).
        name, source: the new model's ``name`` and ``source`` strings.

    Returns:
        The written path (checked by loading it with :func:`ttsim_jax.params.load_model`).
    """
    from ttsim_jax.files.atomic import atomic_write
    from ttsim_jax.files.toml import signed
    from ttsim_jax.params import load_model

    text = signed(config_text(base_path, sections, name=name, source=source))
    out_path = Path(out_path)
    atomic_write(out_path, text.encode("utf-8"))
    load_model(out_path)
    return out_path


def _toml_string(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'
