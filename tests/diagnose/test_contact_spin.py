"""Contact spins under an effect that changes the spin in flight: a segment's spin is its samples'
mean, the spin at its mean sample time; the racket and table errors carry it to the contact.

Closed forms with a linear spin decay (d w / dt = -k w): w(t + dt) = w(t) exp(-k dt)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import effects as fx
from ttsim_jax import load_model
from ttsim_jax.diagnose import candidates as C
from ttsim_jax.diagnose import stages as S
from ttsim_jax.physics.racket import base_response

K = 0.3  # 1/s


def _decay(rate):
    cls = fx.effect_class("spin_decay")
    spec = C.Spec("spin_decay", cls, tuple(cls.PARAMS), False)
    const = dict(start={k: jnp.zeros(p.shape, jnp.float32) for k, p in cls.PARAMS.items()},
                 scale={k: jnp.float32(1.0) for k in cls.PARAMS})
    u = ({"rate": jnp.full((1,), rate, jnp.float32), "quadratic": jnp.zeros((1,), jnp.float32)},)
    return (spec,), (const,), u


def test_contact_spin_is_the_exponential_decay():
    cls = fx.effect_class("spin_decay")
    effect = cls(rate=jnp.float32(K), quadratic=jnp.float32(0.0))
    w = jnp.array([100.0, -250.0, 40.0])
    for dt in (0.2, -0.15):
        got = S.contact_spin((effect,), jnp.zeros(3), w, 0.0, dt)
        np.testing.assert_allclose(got, w * np.exp(-K * dt), rtol=1e-4)
    # no effect with a spin derivative: the spin is unchanged
    np.testing.assert_array_equal(S.contact_spin((), jnp.zeros(3), w, 0.0, 0.2), w)


@pytest.fixture(scope="module")
def racket_contacts():
    """Four racket contacts in a racket frame equal to the world's (racket at rest): the recorded
    spins are the means of the segments, taken dt_in before and dt_out after the contact."""
    model = load_model("conti2026", dtype=jnp.float32)
    radius, mass = model.ball.radius, model.ball.mass
    rng = np.random.default_rng(0)
    n = 4
    v = np.stack([-rng.uniform(3, 8, n), rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)], 1)
    w = rng.uniform(-300, 300, (n, 3))
    d = rng.uniform(-0.03, 0.03, (n, 2))
    dt = rng.uniform(0.1, 0.3, (n, 2))
    v_out, w_out = jax.vmap(lambda a, b, c: base_response(model.racket, a, b, c, radius, mass))(
        jnp.asarray(v, jnp.float32), jnp.asarray(w, jnp.float32), jnp.asarray(d, jnp.float32))
    w_in_mean = w * np.exp(K * dt[:, :1])  # the spin earlier in the incoming flight was higher
    w_out_mean = np.asarray(w_out) * np.exp(-K * dt[:, 1:])
    f = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    c = dict(x=f(np.concatenate([v, w_in_mean, d], 1)), y_obs=f(np.concatenate([v_out, w_out_mean], 1)),
             correction=f(np.zeros((n, 6))), known=f(np.ones(n)), session=jnp.zeros(n, jnp.int32),
             world_in=f(np.concatenate([v, w_in_mean], 1)), world_out=f(np.concatenate([v_out, w_out_mean], 1)),
             rot=f(np.broadcast_to(np.eye(3), (n, 3, 3))), t=f(np.zeros(n)), spin_dt=f(dt))
    return model, c


def test_racket_errors_vanish_with_the_true_decay(racket_contacts):
    model, c = racket_contacts
    with_decay = np.asarray(S.racket_errors(model, *_decay(K), c))
    without = np.asarray(S.racket_errors(model, (), (), (), c))
    # the model without the decay compares spins from other times: metres per second of error
    assert np.max(np.abs(without[:, 3:])) > 0.05
    assert np.max(np.abs(with_decay)) < 2e-3, with_decay
    # a wrong rate leaves an error
    assert np.max(np.abs(np.asarray(S.racket_errors(model, *_decay(0.5 * K), c))[:, 3:])) > 0.01
