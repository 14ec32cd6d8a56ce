"""Per-ball model parameters: which leaves of a model carry a leading (B,) axis.

``model_axes`` is a pytree prefix of the model, as ``jax.vmap``'s ``in_axes``: 0 where a leaf is per
ball, None where it is shared. :func:`per_ball_axes` builds one from dotted paths; the rest is what
the rollout and its sharded form do with it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ttsim_jax.kernel.fused_params import leaf_axes
from ttsim_jax.params import Model


def per_ball_axes(model: Model, *paths: str):
    """The ``model_axes`` that give the leaves under ``paths`` a per-ball (B,) axis.

    Arguments:
        model: the model (only its structure is used).
        *paths: dotted attribute paths, e.g. ``"table.e0"``, ``"aero.rho_air"``, ``"effects"``
            (every effect parameter), ``"residual"`` (the whole network); none means every leaf
            is shared.

    Returns:
        A pytree prefix of ``model`` with 0 under ``paths`` and None elsewhere, for
        :func:`rollout`'s ``model_axes``.
    """
    axes = jax.tree.map(lambda _: None, model)
    for path in paths:
        names = path.split(".")

        def setter(node, names):
            if not names:
                return 0
            head, rest = names[0], names[1:]
            if isinstance(node, tuple):
                return tuple(setter(v, rest) if str(i) == head else v for i, v in enumerate(node))
            if not hasattr(node, head):
                raise ValueError(f"per_ball_axes: the model has no field {path!r}")
            return node.replace(**{head: setter(getattr(node, head), rest)})

        axes = setter(axes, names)
    return axes


def resolve_axes(model: Model, model_axes):
    """The ``model_axes`` a rollout takes (None: every leaf shared; 0 or True: every leaf per ball;
    else a pytree prefix of the model) as a pytree prefix."""
    if model_axes is None:
        return jax.tree.map(lambda _: None, model)
    if model_axes == 0 or model_axes is True:
        return jax.tree.map(lambda _: 0, model)
    return model_axes


def check_per_ball(model, axes, batch: int):
    """Refuses, naming the leaf, a per-ball leaf whose leading axis is not the batch's."""
    leaves, treedef = jax.tree_util.tree_flatten_with_path(model)
    flat_axes = leaf_axes(model, axes)
    # flattened along the model's own structure: a field that is None in the model (no leaf) must
    # not shift the axes of the leaves after it
    for (path, leaf), ax in zip(leaves, treedef.flatten_up_to(flat_axes)):
        if ax == 0 and (jnp.ndim(leaf) == 0 or jnp.shape(leaf)[0] != batch):
            raise ValueError(f"model leaf {jax.tree_util.keystr(path)} is per ball but has shape "
                             f"{jnp.shape(leaf)}; its leading axis must be the batch ({batch})")


class StaticAxes:
    """A pytree of per-ball axes (None / 0 leaves) as a hashable static argument of the jitted core."""

    def __init__(self, tree):
        leaves, self.treedef = jax.tree_util.tree_flatten(tree, is_leaf=lambda x: x is None)
        self.leaves = tuple(leaves)

    def __hash__(self):
        return hash((self.treedef, self.leaves))

    def __eq__(self, other):
        return isinstance(other, StaticAxes) and (self.treedef, self.leaves) == (other.treedef, other.leaves)

    def tree(self):
        return jax.tree_util.tree_unflatten(self.treedef, self.leaves)


def split_per_ball(model, axes):
    """(per-ball leaves, rebuild(per_ball_leaves) -> model): the model's leaves with a (B,) axis."""
    leaves, treedef = jax.tree_util.tree_flatten(model)
    flags = jax.tree.leaves(jax.tree.map(lambda ax, sub: jax.tree.map(lambda _: ax == 0, sub), axes, model,
                                         is_leaf=lambda x: x is None))
    per_ball = [leaf for leaf, f in zip(leaves, flags) if f]

    def rebuild(new):
        it = iter(new)
        return jax.tree_util.tree_unflatten(treedef, [next(it) if f else leaf for leaf, f in zip(leaves, flags)])

    return per_ball, rebuild
