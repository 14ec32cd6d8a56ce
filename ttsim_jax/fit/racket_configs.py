"""The racket contact fitted per racket configuration (blade, sponge, rubber), judged on held-out
contacts against the paper's constants and against the plainest model-free baseline.

For each configuration a dataset names (:mod:`ttsim_jax.data.racket_configs`), on its training
contacts:

* the updated base model's (e0, e1, et0, et1, e_s) by least squares (:func:`ttsim_jax.fit.racket.fit_racket`);
* the paper's residual network on what that fitted base leaves (:func:`ttsim_jax.fit.network_training.train_residual`:
  the Gaussian likelihood, the distance-based attenuation), optional;
* a quadratic least-squares regression of the outgoing (v~+, w~+) on the incoming (v~, w~)
  (:func:`quadratic_regression`): no physics at all. A physics model that loses to it has not
  earned its form; where the fitted base loses to it and the network closes the gap, the base
  model's form is the limit (:func:`form_limit`).

The held-out contacts (:func:`held_out`): a random ``test_fraction`` of each configuration
(seeded), or every contact at one tilt of the rig (``hold_tilt``: the incoming state's region the
fit never saw, since the tilt sets the incidence angle).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Callable

import jax.numpy as jnp
import numpy as np

from ttsim_jax.data import racket_configs
from ttsim_jax.fit.racket import PARAMETERS, fit_racket, predict, racket_section
from ttsim_jax.fit.racket_arrays import contact_arrays, model_and_name

#: Ridge penalty of the quadratic regression, per training contact, on standardised features.
RIDGE = 1e-3
#: k-means centres of each configuration's network (its attenuation's distances): one number for all,
#: so that every configuration's network has the same shapes and swapping rubbers (in a rollout, in
#: ReturnBall's parameters) never recompiles; fewer only for a configuration with fewer bounces.
CLUSTERS = 100
#: The fitted base model is "limited by its form" where the model-free regression's held-out median
#: |dw| is below this fraction of the fitted base's.
FORM_LIMIT = 0.8


def held_out(configs, tilts, *, test_fraction: float = 0.2, seed: int = 0, hold_tilt: float | None = None) -> np.ndarray:
    """(N,) bool: the held-out contacts. ``hold_tilt`` None: a random ``test_fraction`` of each
    configuration (at least one contact), drawn with ``seed``; else every contact at that tilt [deg]."""
    configs = np.asarray(configs, object)
    if hold_tilt is not None:
        return np.isclose(np.asarray(tilts, np.float64), float(hold_tilt))
    if not 0.0 < test_fraction < 1.0:
        raise ValueError(f"test_fraction = {test_fraction!r}: must be in (0, 1)")
    rng = np.random.default_rng(seed)
    out = np.zeros(len(configs), bool)
    for c in sorted(set(configs.tolist())):
        idx = np.flatnonzero(configs == c)
        out[rng.permutation(idx)[:max(1, int(round(test_fraction * len(idx))))]] = True
    return out


def _quadratic_features(x, mean, scale) -> np.ndarray:
    z = (np.asarray(x, np.float64) - mean) / scale
    n = len(z)
    cols = [np.ones(n)] + [z[:, i] for i in range(z.shape[1])]
    cols += [z[:, i] * z[:, j] for i in range(z.shape[1]) for j in range(i, z.shape[1])]
    return np.stack(cols, 1)


def quadratic_regression(x_train, y_train, x_test, ridge: float = RIDGE) -> np.ndarray:
    """Predictions (M, 6) at ``x_test`` of a least-squares regression of ``y_train`` (N, 6) on the
    constant, linear and quadratic terms of the standardised ``x_train`` (N, k), with a ridge
    penalty ``ridge * N`` (so constant columns, as a planar rig's v~_z, do no harm)."""
    x_train = np.asarray(x_train, np.float64)
    mean, scale = x_train.mean(0), x_train.std(0)
    scale = np.where(scale > 0, scale, 1.0)
    f = _quadratic_features(x_train, mean, scale)
    coef = np.linalg.solve(f.T @ f + ridge * len(f) * np.eye(f.shape[1]), f.T @ np.asarray(y_train, np.float64))
    return _quadratic_features(x_test, mean, scale) @ coef


def errors(pred, y_obs) -> dict:
    """Median |dv| [m/s] and |dw| [rad/s] (norms of the post-contact errors), and the normal (x~)
    and tangential parts of each (:func:`error_medians` of ``pred - y_obs``)."""
    return error_medians(np.asarray(pred, np.float64) - np.asarray(y_obs, np.float64))


def error_medians(e) -> dict:
    """:func:`errors`' medians of signed racket-frame post-contact errors ``e`` (N, >= 6)."""
    e = np.asarray(e, np.float64)
    if not len(e):
        return dict(dv=math.nan, dw=math.nan, dv_normal=math.nan, dv_tangential=math.nan, dw_normal=math.nan,
                    dw_tangential=math.nan)
    med = lambda a: float(np.median(a))  # noqa: E731
    return dict(dv=med(np.linalg.norm(e[:, :3], axis=1)), dw=med(np.linalg.norm(e[:, 3:6], axis=1)),
                dv_normal=med(np.abs(e[:, 0])), dv_tangential=med(np.linalg.norm(e[:, 1:3], axis=1)),
                dw_normal=med(np.abs(e[:, 3])), dw_tangential=med(np.linalg.norm(e[:, 4:6], axis=1)))


def form_limit(row: dict) -> str:
    """One sentence: whether the fitted base model's form limits it on this configuration."""
    fit, quad = row["test"]["fitted"]["dw"], row["test"]["quadratic"]["dw"]
    if not (math.isfinite(fit) and math.isfinite(quad)):
        return "not judged (no held-out contact)"
    if quad < FORM_LIMIT * fit:
        return (f"the base model's form is the limit: a model-free quadratic regression leaves {quad:.1f} rad/s "
                f"where the fitted base leaves {fit:.1f}")
    return f"the fitted base is within {100 * (1 - FORM_LIMIT):.0f} % of the model-free regression ({fit:.1f} against {quad:.1f} rad/s)"


@dataclasses.dataclass
class ConfigFit:
    """What :func:`fit_configs` found for one configuration.

    Attributes:
        name: the configuration; description: its blade, sponge, rubber, rubber type.
        values, stderr, bounds: the fitted base model (as :class:`~ttsim_jax.fit.racket.RacketFit`).
        racket_toml: the ``[racket]`` section of the fitted base.
        network: the trained residual network (None without one).
        report: ``n_train``, ``n_test``, ``test`` {model: :func:`errors`}, ``form``.
    """

    name: str
    description: dict
    values: dict
    stderr: dict
    bounds: list
    racket_toml: str
    network: object
    report: dict


def fit_configs(ds, model="conti2026", *, test_fraction: float = 0.2, seed: int = 0, hold_tilt: float | None = None,
                network: bool = True, max_epochs: int = 300, patience: int = 40, configs=None,
                max_train: int | None = None, progress: Callable[[str], None] = lambda s: None) -> list[ConfigFit]:
    """Fits the racket contact per configuration of ``ds`` (see the module docstring).

    Arguments:
        ds: a dataset whose racket states name their configuration (``rackets.config``).
        model: the base model (bundled name, TOML path or Model): its constants are "paper".
        test_fraction, seed, hold_tilt: the held-out contacts (:func:`held_out`).
        network: also train the residual network per configuration (about 10 s each on 2 cores).
        max_epochs, patience: its training length and early stopping.
        configs: only these configurations (default: all the dataset names).
        max_train: at most this many training contacts per configuration (a seeded draw; the held-out
            ones unchanged): what the fits do with fewer bounces.
        progress: called with one line per configuration.

    Returns:
        One :class:`ConfigFit` per configuration, in name order.
    """
    from ttsim_jax.fit.network_config import TrainConfig
    from ttsim_jax.fit.network_evaluation import predict as network_predict
    from ttsim_jax.fit.network_training import train_residual
    from ttsim_jax.kernel.ball_step import ball_properties
    from ttsim_jax.physics.network import ResidualConfig

    m, _ = model_and_name(model)
    radius, mass = (float(v) for v in ball_properties(m))
    a = contact_arrays(ds, m, n_inputs=8)
    names, _, tilts = racket_configs.of_events(ds, a.event_id)
    if not any(names != ""):
        raise ValueError("fit_configs: the dataset's racket states name no configuration (rackets.config)")
    test = held_out(names, tilts, test_fraction=test_fraction, seed=seed, hold_tilt=hold_tilt)
    desc = racket_configs.descriptions(ds)
    x, y, y_paper = (np.asarray(v, np.float64) for v in (a.x, a.y_obs, a.y_base))
    out = []
    for name in sorted(set(names.tolist()) - {""}):
        if configs is not None and name not in configs:
            continue
        tr, te = np.flatnonzero((names == name) & ~test), np.flatnonzero((names == name) & test)
        if max_train is not None and len(tr) > max_train:
            tr = np.sort(np.random.default_rng(seed + 1).permutation(tr)[:max_train])
        fit = fit_racket(x[tr], y[tr], m)
        params = fit.params(m.racket)

        def base(rows):
            v, w = predict(params, jnp.asarray(x[rows], jnp.float32), radius, mass)
            return np.concatenate([np.asarray(v), np.asarray(w)], 1).astype(np.float64)

        y_fit_tr, y_fit_te = base(tr), base(te)
        test_errors = dict(paper=errors(y_paper[te], y[te]), fitted=errors(y_fit_te, y[te]),
                           quadratic=errors(quadratic_regression(x[tr, :6], y[tr], x[te, :6]), y[te]))
        net = None
        if network:
            # at most three quarters of the contacts: the network trains on 80 % of them
            config = ResidualConfig(n_inputs=8, n_clusters=min(CLUSTERS, max(2, (3 * len(tr)) // 4)))
            net, _ = train_residual(x[tr], y_fit_tr, y[tr], config, TrainConfig(max_epochs=max_epochs, patience=patience,
                                                                              split=(0.8, 0.15, 0.05), seed=seed),
                                    progress=False)
            pred, _, _ = network_predict(net, x[te].astype(np.float32), y_fit_te.astype(np.float32))
            test_errors["fitted+network"] = errors(pred, y[te])
        report = dict(n_train=int(len(tr)), n_test=int(len(te)), test=test_errors)
        report["form"] = form_limit(report)
        out.append(ConfigFit(name=name, description=desc.get(name, {}), values=fit.values, stderr=fit.stderr,
                             bounds=fit.bounds, racket_toml=racket_section(m.racket, fit)["racket"], network=net,
                             report=report))
        t = test_errors
        progress(f"{name}: {len(tr)} train, {len(te)} held out; median |dw| paper {t['paper']['dw']:.1f}, fitted "
                 f"{t['fitted']['dw']:.1f}" + (f", +network {t['fitted+network']['dw']:.1f}" if network else "")
                 + f", quadratic {t['quadratic']['dw']:.1f} rad/s")
    return out


def write_racket_file(fit: ConfigFit, folder, source: str, seed: int = 0) -> Path:
    """Writes ``fit`` as a racket file ``folder/NAME.toml`` (+ ``NAME.ttres``, its network, if it has
    one): what ``load_model(model, racket=path)`` and a task's ``racket_config`` load. Returns the path."""
    from ttsim_jax.files.atomic import atomic_write
    from ttsim_jax.physics.network_checkpoint import save_residual

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    d, t = fit.description, fit.report["test"]
    what = f"{d.get('blade', '')}, {d.get('sponge_mm', '')} mm {d.get('rubber', '')} ({d.get('rubber_type', '')})" if d else ""
    held = ", ".join(f"{k} {v['dv']:.3f} m/s {v['dw']:.1f} rad/s" for k, v in t.items())
    lines = [f"# {fit.name}: {what}" if what else f"# {fit.name}",
             f"# The updated base model fitted on {fit.report['n_train']} bounces (seed {seed}); held-out "
             f"({fit.report['n_test']}) median |dv|, |dw|: {held}.",
             "schema = 1", f'name = "{fit.name}"']
    if what:
        lines.append(f'description = "{what}"')
    lines.append(f'source = "{source}"')
    if fit.network is not None:
        save_residual(folder / f"{fit.name}.ttres", fit.network, metadata=dict(config=fit.name, seed=seed,
                                                                               n_train=fit.report["n_train"]))
        lines.append(f'network = "{fit.name}.ttres"                # residual network trained on the same bounces')
    path = folder / f"{fit.name}.toml"
    atomic_write(path, ("\n".join(lines + ["", fit.racket_toml.rstrip()]) + "\n").encode())
    return path


def best(report: dict) -> str:
    """The fitted model (of "fitted", "fitted+network") with the smallest held-out median |dw|."""
    fitted = {k: v["dw"] for k, v in report["test"].items() if k.startswith("fitted") and math.isfinite(v["dw"])}
    return min(fitted, key=fitted.get) if fitted else "fitted"


__all__ = ["ConfigFit", "FORM_LIMIT", "PARAMETERS", "best", "errors", "fit_configs", "form_limit", "held_out",
           "quadratic_regression", "write_racket_file"]
