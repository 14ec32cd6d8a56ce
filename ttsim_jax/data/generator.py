"""Old import path of the reality generator, kept for one release.

The generator moved to :mod:`ttsim_jax.reality` (configuration, games, strokes, contact inversion,
assembly, truth files); the quaternion conversion to :mod:`ttsim_jax.physics.rotations`. This
module re-exports the public names it held, with a :class:`DeprecationWarning` on import.
"""

import warnings

from ttsim_jax.physics.rotations import matrix_to_quat
from ttsim_jax.reality.assembly import GENERATOR_VERSION, Generated
from ttsim_jax.reality.config import (
    BYTES_PER_ROW,
    PRESETS,
    SECONDS_PER_HIT,
    GeneratorConfig,
    GeneratorError,
    config_from_toml,
    make_config,
    memory_bytes,
)
from ttsim_jax.reality.game import OPPONENT, PLAYERS, ROBOT
from ttsim_jax.reality.generation import generate, rerecord
from ttsim_jax.reality.inversion import invert_contact
from ttsim_jax.reality.strokes import AIM_HORIZON, AIM_STEP, NET_TOP, sample_contact_points
from ttsim_jax.reality.truth import Truth, load_truth, write

warnings.warn("ttsim_jax.data.generator moved to ttsim_jax.reality; import from ttsim_jax.reality (the quaternion "
              "conversion from ttsim_jax.physics.rotations); the old path goes in the next release",
              DeprecationWarning, stacklevel=2)

__all__ = ["AIM_HORIZON", "AIM_STEP", "BYTES_PER_ROW", "GENERATOR_VERSION", "NET_TOP", "OPPONENT", "PLAYERS", "PRESETS",
           "ROBOT", "SECONDS_PER_HIT", "Generated", "GeneratorConfig", "GeneratorError", "Truth", "config_from_toml",
           "generate", "invert_contact", "load_truth", "make_config", "matrix_to_quat", "memory_bytes", "rerecord",
           "sample_contact_points", "write"]
