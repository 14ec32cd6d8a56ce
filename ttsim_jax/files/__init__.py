"""What the package reads and writes on disk: crash-safe writes (:mod:`~ttsim_jax.files.atomic`),
the checkpoint container (:mod:`~ttsim_jax.files.checkpoint`), TOML reading
(:mod:`~ttsim_jax.files.toml`) and the caches (:mod:`~ttsim_jax.files.cache`; traced programs:
:mod:`~ttsim_jax.files.programs`).

The lowest layer: nothing here imports the physics, and nothing imports JAX when it is imported.
"""
