"""Registers ``ttsim/ReturnBall-v0`` with gymnasium without importing gymnasium.

``import ttsim_jax`` stays light: where gymnasium is already imported the environment is registered
at once; otherwise the registration runs right after gymnasium's own import, whenever that happens
(an import hook on ``sys.meta_path`` that removes itself). Either way the entry points are strings,
so the environment package itself is imported only by ``gymnasium.make``.
"""

from __future__ import annotations

import importlib.abc
import importlib.util
import sys

RETURN_BALL_ID = "ttsim/ReturnBall-v0"


def register_envs() -> None:
    """Registers ``ttsim/ReturnBall-v0`` (``gymnasium.make`` and ``gymnasium.make_vec``) once;
    imports gymnasium."""
    try:
        import gymnasium
    except ImportError:  # gymnasium is a dependency; without it there is nothing to register with
        return
    if RETURN_BALL_ID in gymnasium.registry:
        return
    gymnasium.register(id=RETURN_BALL_ID, entry_point="ttsim_jax.env.gym:ReturnBallEnv",
                       vector_entry_point="ttsim_jax.env.gym:ReturnBallVectorEnv")


class _AfterGymnasium(importlib.abc.MetaPathFinder):
    """Finds gymnasium as the other finders would, with its module's execution followed by
    :func:`register_envs`."""

    def find_spec(self, name, path=None, target=None):
        if name != "gymnasium":
            return None
        sys.meta_path.remove(self)  # once: the real finders look it up, and no later import sees this
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            register_envs()

        spec.loader.exec_module = exec_module  # this spec's own loader instance
        return spec


def register_when_imported() -> None:
    """Registers the environment now if gymnasium is imported, else right after it is."""
    if "gymnasium" in sys.modules:
        register_envs()
    elif not any(isinstance(f, _AfterGymnasium) for f in sys.meta_path):
        sys.meta_path.insert(0, _AfterGymnasium())
