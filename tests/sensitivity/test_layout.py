"""Where a shot's inputs sit in the flat vector the Jacobians are taken against, and which columns
of the outcome each target reads (no kernel compile here)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import load_model
from ttsim_jax.fit.network_config import load_residual_config
from ttsim_jax.params import config_dir
from ttsim_jax.physics.network import init_model
from ttsim_jax.sensitivity.cases import WINDOW
from ttsim_jax.sensitivity.jacobians import STATE_GROUPS, group_of, horizon_plan, horizons, layout_of
from ttsim_jax.sensitivity.targets import COLUMNS, TARGETS, Outcome, columns_of, for_target


def test_residual_network_weights_are_one_group():
    """Every float of the racket residual network (weights, normalisation statistics) is a column
    of the group ``residual.network``, and nothing else is."""
    config = load_residual_config(config_dir() / "residual" / "conti2026.toml")
    net = init_model(config, jax.random.key(0))
    base = layout_of(load_model("conti2026", dtype=jnp.float64))
    layout = layout_of(load_model("conti2026", dtype=jnp.float64, residual=net))
    groups, columns = layout.groups(), layout.columns()
    n_net = sum(np.size(a) for a in jax.tree.leaves(net) if jnp.issubdtype(jnp.asarray(a).dtype, jnp.floating))
    assert n_net > 100
    assert (groups == "residual.network").sum() == n_net == layout.n_columns - base.n_columns
    assert all(c.startswith("residual.") for c, g in zip(columns, groups) if g == "residual.network")
    assert not any(c.startswith("residual.") for c, g in zip(columns, groups) if g != "residual.network")
    # the rest of the layout is the base model's, in the same order
    assert [c for c, g in zip(columns, groups) if g != "residual.network"] == base.columns()
    assert list(dict.fromkeys(groups))[:len(STATE_GROUPS)] == list(STATE_GROUPS)


@pytest.mark.parametrize("name, group", [
    ("table.e0", "table.restitution"), ("table.net_height", "table.geometry"), ("aero.drag.cd", "aero.drag"),
    ("residual.variables.params.0", "residual.network"), ("racket.k_n", "racket.params")])
def test_group_of_parameter_paths(name, group):
    assert group_of(name) == group


def test_targets_are_columns_of_the_one_program():
    """Each target keeps its own columns; the net clearance also needs the net crossed."""
    for target, components in TARGETS.items():
        assert tuple(COLUMNS[i] for i in columns_of(target)) == components
    values = np.arange(10.0).reshape(2, 5) + 1.0
    out = Outcome(values=values, sequence=np.array([[2, 1], [2, 1]]), valid=np.array([True, True]),
                  crossed=np.array([True, False]), steps=np.array([300, 400]))
    land = for_target(out, "landing")
    np.testing.assert_array_equal(land.values, values[:, :2])
    assert land.valid.tolist() == [True, True]
    net = for_target(out, "net_clearance")
    np.testing.assert_array_equal(net.values, [[5.0], [0.0]])
    assert net.valid.tolist() == [True, False]
    np.testing.assert_array_equal(for_target(out, "bounce_speed").values, values[:, 3:4])
    with pytest.raises(ValueError, match="unknown target 'apex'"):
        columns_of("apex")


def test_horizon_plan_groups_landed_shots_by_the_steps_they_need():
    """Only the shots that land are differentiated, the shortest needs together, each group through
    the shortest horizon (of the buckets) that holds its longest shot plus the margin."""
    assert horizons(1200, 4) == (300, 600, 900, 1200) and horizons(350, 4) == (88, 175, 263, 350)
    assert horizons(1200, 1) == (1200,)
    # flight steps needed (after the racket window, margin of 2 included): 100 500 250 900 901 50
    steps = np.array([98, 498, 248, 898, 899, 48, 30]) + WINDOW
    valid = np.array([True, True, True, True, True, True, False])
    plan = horizon_plan(steps, valid, 1200, 2, 4)
    assert [r.tolist() for r, _ in plan] == [[5, 0], [2, 1], [3, 4]]
    assert [h for _, h in plan] == [300, 600, 1200]
    # a need of exactly a bucket stays in it; one step more goes to the next
    assert [h for _, h in horizon_plan(steps, valid, 1200, 1, 4)] == [300, 300, 300, 600, 900, 1200]
    assert [h for _, h in horizon_plan(steps, valid, 1200, 6, 1)] == [1200]
    assert horizon_plan(steps, np.zeros(7, bool), 1200, 2, 4) == []
