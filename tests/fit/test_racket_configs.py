"""The racket contact fitted per configuration: the model-free baseline, the held-out split, the fit
on a synthetic rig with known coefficients, and the bundled fitted configurations loading by name
and running in the rally kernel."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import Ball, Racket, simulate
from ttsim_jax.fit import racket_configs as rc
from ttsim_jax.params import ConfigError, available_rackets, load_model
from ttsim_jax.physics.events import KIND_NAMES
from ttsim_jax.reality import synthetic_rig_dataset


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


def test_fit_configs_recovers_each_configurations_coefficients():
    truth = {"grippy": [0.85, -0.01, 0.75, -0.01, 0.6], "slick": [0.7, -0.005, 0.2, -0.002, 0.3]}
    fits = rc.fit_configs(synthetic_rig_dataset(truth, 300, 0), "conti2026", network=False)
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
    for name in names:
        m = load_model("conti2026", racket=name)
        assert load_model(f"conti2026+{name}").name == m.name  # the same model by its name
        assert m.name == f"conti2026+{name}" and m.residual is not None and m.racket.kind == "updated"
        base_only = load_model("conti2026", racket=name, racket_network=False)
        assert base_only.residual is None and float(base_only.racket.e0) == float(m.racket.e0)
        r = run(m.replace(name="rubber"))  # the name is static: one shared name, one program for all ten
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
    with pytest.raises(ConfigError, match="unknown racket 'racket_99'"):
        load_model("conti2026+racket_99")


def test_ttsim_fit_per_racket_writes_racket_files_that_load(tmp_path, capsys):
    from ttsim_jax.cli import main
    from ttsim_jax.data import save

    truth = {"grippy": [0.85, -0.01, 0.75, -0.01, 0.6], "slick": [0.7, -0.005, 0.2, -0.002, 0.3]}
    data = save(synthetic_rig_dataset(truth, 200, 1), tmp_path / "rig")
    assert main(["fit", "--data", str(data), "--out", str(tmp_path / "fit"), "--stages", "racket", "--per-racket",
                 "--quiet"]) == 0
    assert "grippy: wrote" in capsys.readouterr().out
    for name, theta in truth.items():
        m = load_model("conti2026", racket=tmp_path / "fit.rackets" / f"{name}.toml")
        assert m.residual is None  # no residual stage: no network
        np.testing.assert_allclose([float(getattr(m.racket, k)) for k in rc.PARAMETERS], theta, atol=3e-3)


def test_a_model_with_a_racket_by_name_is_never_read_as_the_bare_model():
    from ttsim_jax.cli.options import model_name_or_file
    from ttsim_jax.evaluate.stages import resolve_models
    from ttsim_jax.params import resolve_model_path

    (name, m), = resolve_models(["conti2026+racket_05"])
    assert name == "conti2026+racket_05" and m.residual is not None
    assert float(m.racket.et0) == float(load_model("conti2026", racket="racket_05").racket.et0)
    assert float(m.racket.et0) != float(load_model("conti2026").racket.et0)
    assert model_name_or_file("conti2026+racket_05") == "conti2026+racket_05"
    with pytest.raises(ConfigError, match="has no model file of its own"):
        resolve_model_path("conti2026+racket_05")  # whoever reads the file would drop the racket
