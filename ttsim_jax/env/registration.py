"""Registers the environments with gymnasium (run when ``ttsim_jax`` is imported)."""

from __future__ import annotations

RETURN_BALL_ID = "ttsim/ReturnBall-v0"


def register_envs() -> None:
    """Registers ``ttsim/ReturnBall-v0`` (``gymnasium.make`` and ``gymnasium.make_vec``) once."""
    try:
        import gymnasium
    except ImportError:  # gymnasium is a dependency; without it there is nothing to register with
        return
    if RETURN_BALL_ID in gymnasium.registry:
        return
    gymnasium.register(id=RETURN_BALL_ID, entry_point="ttsim_jax.env.gym:ReturnBallEnv",
                       vector_entry_point="ttsim_jax.env.gym:ReturnBallVectorEnv")
