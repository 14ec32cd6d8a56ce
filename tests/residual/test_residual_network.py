"""Residual network evaluation: attenuation, gathered evaluation, jit behaviour, input checks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax.errors import ConfigError
from ttsim_jax.fit.network_stats import kmeans
from ttsim_jax.reality.synthetic_contacts import sample_racket_inputs
from ttsim_jax.physics.network import (PAPER_BETA, ResidualConfig, beta_from_distance, gathered_residual, init_model,
                                       residual_outputs)

TINY = ResidualConfig(trunk=(16, 16), head_width=8, n_clusters=20, dropout=0.1)


def _random_model(config, seed):
    """A model with random (non-trivial) parameters and statistics, no training needed."""
    model = init_model(config, jax.random.key(seed))
    rng = np.random.default_rng(seed + 100)  # host-side noise: op-by-op device calls are slow
    variables = jax.tree_util.tree_map(
        lambda a: jnp.asarray(np.asarray(a) + 0.3 * rng.normal(size=a.shape).astype(np.asarray(a).dtype)),
        model.variables)
    variables["batch_stats"] = jax.tree_util.tree_map(jnp.abs, variables["batch_stats"])
    x = jnp.asarray(sample_racket_inputs(500, seed))[:, :config.n_inputs]
    x_min, x_max = x.min(0), x.max(0)
    centres = kmeans((x[:, :6] - x_min[:6]) / (x_max[:6] - x_min[:6]), config.n_clusters, jax.random.key(seed))
    return model.replace(variables=variables, x_min=x_min, x_max=x_max,
                         y_scale=jnp.asarray([0.3, 0.3, 0.3, 30.0, 30.0, 30.0]),
                         centres=centres, beta_coef=jnp.asarray([7.282, 4.0, 0.052])), x


@pytest.fixture(scope="module")
def model_and_x():
    return _random_model(TINY, 0)


def _close(a, b):
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-5)


def test_outputs_shapes_and_positivity(model_and_x):
    model, x = model_and_x
    out = residual_outputs(model, x)
    assert set(out) == {"dv", "dw", "sigma_v", "sigma_w", "beta"}
    assert out["dv"].shape == (len(x), 3) and out["beta"].shape == (len(x),)
    assert bool(jnp.all(out["sigma_v"] > 0)) and bool(jnp.all(out["sigma_w"] > 0))
    raw = residual_outputs(model, x, attenuate=False)
    _close(out["dv"], out["beta"][:, None] * raw["dv"])
    _close(out["dw"], out["beta"][:, None] * raw["dw"])


def test_beta_one_near_data_zero_far(model_and_x):
    model, x = model_and_x
    beta = residual_outputs(model, x)["beta"]
    assert float(jnp.mean(beta)) > 0.9
    span = model.x_max - model.x_min
    far = model.x_max + 3.0 * span
    assert float(jnp.max(residual_outputs(model, jnp.tile(far, (4, 1)))["beta"])) == 0.0
    # the authors' coefficients: 1 up to distance 0.150, 0 from 0.383
    coef = jnp.asarray(PAPER_BETA)
    beta = beta_from_distance(jnp.asarray([0.0, 0.149, 0.384, 2.0]), coef)
    np.testing.assert_allclose(beta, [1, 1, 0, 0], atol=1e-3)


@pytest.mark.parametrize("n_masked,capacity", [(0, 8), (5, 8), (8, 8), (23, 8), (40, 40)])
def test_gathered_equals_full_evaluation(model_and_x, n_masked, capacity):
    model, x = model_and_x
    x = x[:40]
    mask = np.zeros(40, bool)
    mask[np.random.default_rng(n_masked).choice(40, n_masked, replace=False)] = True
    fn = jax.jit(gathered_residual, static_argnames=("capacity", "sample"))
    got = fn(model, x, jnp.asarray(mask), capacity=capacity)
    ref = residual_outputs(model, x)
    for k in ref:
        _close(np.asarray(got[k])[mask], np.asarray(ref[k])[mask])
        assert np.all(np.asarray(got[k])[~mask] == 0.0), k


def test_gathered_sampling_is_branch_independent(model_and_x):
    model, x = model_and_x
    x = x[:30]
    key = jax.random.key(7)
    mask = np.zeros(30, bool)
    mask[[1, 4, 9, 20]] = True
    fn = jax.jit(gathered_residual, static_argnames=("capacity", "sample"))
    small = fn(model, x, jnp.asarray(mask), capacity=4, key=key, sample=True)   # buffer path
    big = fn(model, x, jnp.asarray(mask), capacity=2, key=key, sample=True)     # overflow path
    eps = np.asarray(jax.random.normal(key, (30, 6), x.dtype))  # the documented draw: x's dtype
    raw = residual_outputs(model, x, attenuate=False)
    beta = np.asarray(raw["beta"])[:, None]
    expect_dv = beta * (np.asarray(raw["dv"]) + np.asarray(raw["sigma_v"]) * eps[:, :3])
    for out in (small, big):
        _close(np.asarray(out["dv"])[mask], expect_dv[mask])
        assert np.all(np.asarray(out["dw"])[~mask] == 0.0)
    with pytest.raises(ValueError, match="PRNG key"):
        gathered_residual(model, x, jnp.asarray(mask), 4, sample=True)


def test_no_recompilation_when_swapping_parameters():
    traces = []

    @jax.jit
    def f(model, x):
        traces.append(1)
        return residual_outputs(model, x)["dv"]

    @jax.jit
    def g(model, x, mask):
        traces.append(2)
        return gathered_residual(model, x, mask, capacity=4)["dw"]

    m1, x = _random_model(TINY, 1)
    m2, _ = _random_model(TINY, 2)
    mask = jnp.arange(len(x)) % 7 == 0
    a, b = f(m1, x), f(m2, x)
    g(m1, x, mask), g(m2, x, mask)
    assert traces == [1, 2]
    assert not np.allclose(np.asarray(a), np.asarray(b))


def test_differentiable_through_gathered(model_and_x):
    model, x = model_and_x
    mask = jnp.arange(len(x)) % 3 == 0

    def loss(variables, x):
        return jnp.sum(gathered_residual(model.replace(variables=variables), x, mask, capacity=200)["dv"] ** 2)

    gp, gx = jax.grad(loss, argnums=(0, 1))(model.variables, x)
    leaves = jax.tree_util.tree_leaves(gp)
    assert all(bool(jnp.all(jnp.isfinite(v))) for v in leaves)
    assert any(float(jnp.abs(v).max()) > 0 for v in leaves)
    assert bool(jnp.all(jnp.isfinite(gx)))
    assert bool(jnp.all(gx[~mask] == 0.0))


def test_vmap_over_parameter_sets():
    m1, x = _random_model(TINY, 3)
    m2, _ = _random_model(TINY, 4)
    stacked = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), m1, m2)
    out = jax.vmap(lambda m: residual_outputs(m, x[:10])["dv"])(stacked)
    _close(out[1], residual_outputs(m2, x[:10])["dv"])


def test_six_input_variant():
    cfg = ResidualConfig(n_inputs=6, trunk=(16, 16), head_width=8, n_clusters=10)
    model, x = _random_model(cfg, 5)
    assert x.shape[1] == 6
    out = jax.jit(gathered_residual, static_argnames=("capacity", "sample"))(model, x, x[:, 0] < -10.0, capacity=16)
    assert out["dv"].shape == (len(x), 3)
    with pytest.raises(ValueError, match=r"expects \(N, 6\)"):
        residual_outputs(model, jnp.zeros((3, 8)))


def test_bad_inputs_are_named(model_and_x):
    model, x = model_and_x
    with pytest.raises(ValueError, match=r"residual_outputs: x has shape \(5, 6\).*\(N, 8\)"):
        residual_outputs(model, jnp.zeros((5, 6)))
    with pytest.raises(ValueError, match="mask"):
        gathered_residual(model, x, jnp.ones(3, bool), 4)
    with pytest.raises(ValueError, match="capacity"):
        gathered_residual(model, x, jnp.ones(len(x), bool), 0)
    with pytest.raises(ConfigError, match="n_inputs = 7"):
        ResidualConfig(n_inputs=7)


def test_kmeans_finds_separated_blobs():
    rng = np.random.default_rng(0)
    truth = np.array([[0.1] * 6, [0.9] * 6, [0.1, 0.9] * 3, [0.9, 0.1] * 3])
    pts = np.concatenate([t + 0.01 * rng.standard_normal((200, 6)) for t in truth]).astype(np.float32)
    centres = np.asarray(kmeans(jnp.asarray(pts), 4, jax.random.key(0), iters=20))
    d = np.linalg.norm(centres[:, None] - truth[None], axis=-1)
    assert np.all(d.min(axis=0) < 0.01)
    with pytest.raises(ValueError, match="cannot make"):
        kmeans(jnp.asarray(pts[:3]), 4, jax.random.key(0))
