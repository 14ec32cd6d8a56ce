"""jax.grad of the landing point against central finite differences (float64).

Scenario: a topspin ball bounces on the table, is returned by a moving, spinning, closed racket and
lands on the other half. The event sequence (table, racket, table) does not change under the small
perturbations, so the landing point is smooth in every parameter and initial-state component.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import Ball, Racket, load_model, simulate
from ttsim_jax.physics.events import RACKET, TABLE

N = 900


def scenario():
    th = np.deg2rad(25)
    rot = np.array([[-np.cos(th), 0, -np.sin(th)], [0, -1, 0], [-np.sin(th), 0, np.cos(th)]])
    rk = Racket.create(jnp.array([1.6, 0.0, 0.2]), rot=jnp.asarray(rot), vel=jnp.array([-0.5, 0.0, 0.1]),
                       ang_vel=jnp.array([0.0, 5.0, 2.0]))
    t = jnp.arange(N)[:, None] * 1e-3
    sched = jax.tree.map(lambda a: jnp.broadcast_to(a, (N,) + a.shape), rk).replace(pos=rk.pos + t * rk.vel)
    ball = Ball.create([[-1.2, 0.0, 0.3]], [[6.0, 0.0, 1.0]], [[0.0, 150.0, 0.0]])
    return ball, sched


def landing(model, ball, sched):
    r = simulate(model, ball, N, racket=sched)
    return r.events.pre.pos[0, 2, :2], r.events.kind[0, :3]


@pytest.mark.slow
@pytest.mark.parametrize("name", ["conti2026", "nakashima2011"])
def test_landing_gradient_matches_finite_differences(name):
    model = load_model(name, dtype=jnp.float64)
    ball, sched = scenario()
    _, kinds = landing(model, ball, sched)
    assert np.asarray(kinds).tolist() == [TABLE, RACKET, TABLE]

    f = jax.jit(lambda m, b: landing(m, b, sched)[0])
    jac_m, jac_b = jax.jit(jax.jacrev(f, argnums=(0, 1)))(model, ball)

    rng = np.random.default_rng(0)
    leaves, treedef = jax.tree.flatten((model, ball))
    jacs = jax.tree.leaves((jac_m, jac_b))  # same order, each (2, *leaf.shape)
    assert len(jacs) == len(leaves)
    checked = nonzero = 0
    for i, (leaf, jac) in enumerate(zip(leaves, jacs)):
        u = rng.standard_normal(leaf.shape)
        scale = max(float(np.mean(np.abs(np.asarray(leaf)))), 1e-3)
        eps = 1e-6 * scale

        def at(sign):
            moved = list(leaves)
            moved[i] = leaf + sign * eps * u
            m, b = jax.tree.unflatten(treedef, moved)
            return np.asarray(f(m, b))

        fd = (at(1) - at(-1)) / (2 * eps)
        ad = np.tensordot(np.asarray(jac), u, axes=u.ndim)
        assert np.all(np.isfinite(ad))
        np.testing.assert_allclose(ad, fd, rtol=1e-2, atol=1e-6 * max(1.0, np.max(np.abs(fd))),
                                   err_msg=f"leaf {i} {jax.tree_util.keystr(jax.tree_util.tree_flatten_with_path((model, ball))[0][i][0])}")
        checked += 1
        nonzero += bool(np.max(np.abs(fd)) > 1e-6)
    assert checked == len(leaves)
    assert nonzero >= 10  # the landing point really depends on many parameters
