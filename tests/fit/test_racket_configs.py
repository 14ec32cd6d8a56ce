"""The racket contact fitted per configuration: the model-free baseline, the held-out split, the fit
on a synthetic rig with known coefficients, and the bundled fitted configurations loading by name
and running in the rally kernel."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import Ball, Racket, simulate
from ttsim_jax.data import Dataset
from ttsim_jax.data.importers import tt_rackets
from ttsim_jax.fit import racket_configs as rc
from ttsim_jax.fit.racket import predict, updated_params
from ttsim_jax.fit.racket_arrays import draw_contact_states
from ttsim_jax.params import ConfigError, available_rackets, load_model
from ttsim_jax.physics.events import KIND_NAMES


def test_quadratic_regression_recovers_a_quadratic_law_exactly():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(200, 6)) * [3, 0, 5, 100, 200, 50]  # a constant column, as a planar rig's
    x[:, 1] = 0.0
    y = np.stack([1 + x[:, 0] * x[:, 2] / 10, x[:, 3] ** 2 / 1e4, -x[:, 4] + 0.5 * x[:, 5], x[:, 0], x[:, 2] ** 2,
                  3 * np.ones(200)], 1)
    xt = rng.normal(size=(50, 6)) * [3, 0, 5, 100, 200, 50]
    xt[:, 1] = 0.0
    yt = np.stack([1 + xt[:, 0] * xt[:, 2] / 10, xt[:, 3] ** 2 / 1e4, -xt[:, 4] + 0.5 * xt[:, 5], xt[:, 0],
                   xt[:, 2] ** 2, 3 * np.ones(50)], 1)
    np.testing.assert_allclose(rc.quadratic_regression(x, y, xt, ridge=1e-12), yt, atol=1e-6 * np.abs(yt).max())


def test_held_out_split():
    names = np.array(["a"] * 100 + ["b"] * 11, object)
    tilts = np.array([0.0, 10.0, 20.0] * 37)
    test = rc.held_out(names, tilts, test_fraction=0.2, seed=3)
    assert test[:100].sum() == 20 and test[100:].sum() == 2
    assert not np.array_equal(test, rc.held_out(names, tilts, test_fraction=0.2, seed=4))
    np.testing.assert_array_equal(rc.held_out(names, tilts, hold_tilt=20.0), tilts == 20.0)
    with pytest.raises(ValueError, match="test_fraction"):
        rc.held_out(names, tilts, test_fraction=1.0)


def _rig(truth: dict, n: int, seed: int):
    """A rig dataset (tt_rackets' layout) of two configurations bouncing through known updated-base
    coefficients, racket at rest, face normal along world z."""
    base = load_model("conti2026").racket
    ids, states, names = [], [], []
    for k, (name, theta) in enumerate(truth.items()):
        v, w, d = draw_contact_states(np.random.default_rng(seed + k), n, 10.0, 400.0)
        x = np.concatenate([v, w, np.zeros((n, 2))], 1)
        vp, wp = predict(updated_params(base, theta), jnp.asarray(x, jnp.float32), 0.02, 2.721e-3)
        racket_frame = np.concatenate([x[:, :6], np.asarray(vp), np.asarray(wp)], 1)
        # racket frame (x~ normal, y~, z~) -> world (y~, z~, x~)
        states.append(racket_frame.reshape(n, 4, 3)[:, :, [1, 2, 0]].reshape(n, 12))
        ids.append((k + 1) * 10000 + np.arange(n))
        names += [name] * n
    ids, s = np.concatenate(ids), np.concatenate(states)
    m = len(ids)
    face = np.tile(tt_rackets.RACKET_POSITION, (m, 1))
    return Dataset.from_arrays(
        np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)),
        events=dict(event_id=ids, session_id=0, t=np.arange(m, dtype=float), kind="racket", pos=face + [0, 0, 0.02]),
        rackets=dict(event_id=ids, pos=face, quat=np.tile(tt_rackets.RACKET_QUAT, (m, 1)), vel=np.zeros((m, 3)),
                     ang_vel=np.zeros((m, 3)), contact=np.zeros((m, 2)), config=np.array(names, object)),
        segments=None, contact_states=dict(event_id=ids, v_in=s[:, 0:3], w_in=s[:, 3:6], v_out=s[:, 6:9], w_out=s[:, 9:12]))


def test_fit_configs_recovers_each_configurations_coefficients():
    truth = {"grippy": [0.85, -0.01, 0.75, -0.01, 0.6], "slick": [0.7, -0.005, 0.2, -0.002, 0.3]}
    fits = rc.fit_configs(_rig(truth, 300, 0), "conti2026", network=False)
    assert [f.name for f in fits] == ["grippy", "slick"]
    for f in fits:
        got = [f.values[k] for k in rc.PARAMETERS]
        np.testing.assert_allclose(got, truth[f.name], atol=2e-3)
        t = f.report["test"]
        assert f.report["n_test"] == 60 and t["fitted"]["dw"] < 0.05 < t["paper"]["dw"]
        assert rc.best(f.report) == "fitted"


def test_every_bundled_racket_loads_by_name_and_runs_in_the_kernel():
    names = available_rackets()
    assert names == [f"racket_{k:02d}" for k in range(1, 11)]
    n = 200
    t = jnp.arange(n)[:, None] * 1e-3
    th = np.deg2rad(20)
    rot = jnp.asarray([[-np.cos(th), 0, -np.sin(th)], [0, -1, 0], [-np.sin(th), 0, np.cos(th)]])
    rk = Racket.create(jnp.array([1.6, 0.0, 0.25]), rot=rot, vel=jnp.array([-1.0, 0.0, 0.5]))
    sched = jax.tree.map(lambda a: jnp.broadcast_to(a, (n,) + a.shape), rk).replace(pos=rk.pos + t * rk.vel)
    ball = Ball.create([[1.1, 0.0, 0.3]], [[5.0, 0.0, 0.5]], [[0.0, 150.0, 0.0]])
    outgoing = {}
    run = jax.jit(lambda m: simulate(m, ball, n, racket=sched))
    for name in ["racket_01", "racket_05", "racket_10"]:
        m = load_model("conti2026", racket=name)
        assert m.name == f"conti2026+{name}" and m.residual is not None and m.racket.kind == "updated"
        base_only = load_model("conti2026", racket=name, racket_network=False)
        assert base_only.residual is None and float(base_only.racket.e0) == float(m.racket.e0)
        r = run(m)
        kinds = np.asarray(r.events.kind[0])
        assert (kinds == KIND_NAMES.index("racket")).any(), kinds
        hit = int(np.flatnonzero(kinds == KIND_NAMES.index("racket"))[0])
        v = np.asarray(r.events.post.vel[0, hit])
        assert np.isfinite(v).all()
        outgoing[name] = v
    # a long-pimpled rubber does not return the ball as an inverted one does
    assert np.linalg.norm(outgoing["racket_01"] - outgoing["racket_05"]) > 0.1
    with pytest.raises(ConfigError, match="unknown racket 'racket_99'"):
        load_model("conti2026", racket="racket_99")
