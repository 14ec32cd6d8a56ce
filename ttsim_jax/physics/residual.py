"""Deprecated: the residual network's former module, kept for one release; importing it warns.

Its names moved, each to a module named after what it holds:

* the network, its configuration and its inference: :mod:`ttsim_jax.physics.network`;
* a network's file (``save_residual``, ``load_residual``, ``checkpoint_metadata``,
  ``model_from_arrays``): :mod:`ttsim_jax.physics.network_checkpoint`;
* the checkpoint container (``read_container``, ``write_container``, ``CheckpointError``):
  :mod:`ttsim_jax.files.checkpoint`; ``ConfigError``: :mod:`ttsim_jax.errors`; ``read_toml``:
  :mod:`ttsim_jax.files.toml`;
* the configuration files (``load_residual_config``, ``residual_config_from_toml``):
  :mod:`ttsim_jax.fit.network_config`;
* the statistics of training (``kmeans``, ``calibrate_beta``, ``population_batch_stats``,
  ``calibration_scale``, ``ONE_SIGMA_COVERAGE``): :mod:`ttsim_jax.fit.network_stats`.
"""

import warnings

from ttsim_jax.errors import ConfigError
from ttsim_jax.files.checkpoint import (CHECKPOINT_MAGIC, CHECKPOINT_VERSION, CheckpointError, read_container,
                                        write_container)
from ttsim_jax.files.toml import read_toml
from ttsim_jax.fit.network_config import CONFIG_TABLES, load_residual_config, residual_config_from_toml
from ttsim_jax.fit.network_stats import (ONE_SIGMA_COVERAGE, calibrate_beta, calibration_scale, kmeans,
                                         population_batch_stats)
from ttsim_jax.physics.network import (N_ATTENUATION_INPUTS, PAPER_BETA, ResidualConfig, ResidualModel, ResidualNet,
                                       attenuation, beta_from_distance, gathered_residual, init_model,
                                       init_variables, model_shapes, nearest_distance, network_outputs,
                                       residual_outputs, sampled_residual, scale_inputs, variable_shapes)
from ttsim_jax.physics.network_checkpoint import (READABLE_MODEL_VERSIONS, checkpoint_metadata, load_residual,
                                                  model_from_arrays, save_residual)

__all__ = [
    "CHECKPOINT_MAGIC", "CHECKPOINT_VERSION", "CONFIG_TABLES", "N_ATTENUATION_INPUTS", "ONE_SIGMA_COVERAGE",
    "PAPER_BETA", "READABLE_MODEL_VERSIONS", "CheckpointError", "ConfigError", "ResidualConfig", "ResidualModel",
    "ResidualNet", "attenuation", "beta_from_distance", "calibrate_beta", "calibration_scale",
    "checkpoint_metadata", "gathered_residual", "init_model", "init_variables", "kmeans", "load_residual",
    "load_residual_config", "model_from_arrays", "model_shapes", "nearest_distance", "network_outputs",
    "population_batch_stats", "read_container", "read_toml", "residual_config_from_toml", "residual_outputs",
    "sampled_residual", "save_residual", "scale_inputs", "variable_shapes", "write_container",
]

warnings.warn("ttsim_jax.physics.residual is deprecated and will be removed in the next release: import from "
              "ttsim_jax.physics.network (the network), ttsim_jax.physics.network_checkpoint (its file), "
              "ttsim_jax.fit.network_config (its TOML config), ttsim_jax.fit.network_stats (training statistics), "
              "ttsim_jax.files.checkpoint (CheckpointError), ttsim_jax.files.toml (read_toml) or ttsim_jax.errors "
              "(ConfigError)",
              DeprecationWarning, stacklevel=2)
