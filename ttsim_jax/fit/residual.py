"""Deprecated: the residual network's former training module, kept for one release; importing it warns.

Its names moved, each to a module named after what it holds:

* training (``train_residual``, ``split_by_contact``, ``gaussian_nll``, ``TRAIN_STATE_KIND``):
  :mod:`ttsim_jax.fit.network_training`;
* the configuration files (``TrainConfig``, ``load_train_config``):
  :mod:`ttsim_jax.fit.network_config`;
* evaluation and sigma calibration (``predict``, ``evaluate_residual``, ``evaluate_by_band``,
  ``calibrate_sigma``, ``contact_errors``, ``distance_bands``, ``COMPONENTS``, ``ERROR_NAMES``):
  :mod:`ttsim_jax.fit.network_evaluation`;
* the synthetic contact set and the recovery experiment (``make_synthetic_contacts``,
  ``recovery_experiment``, ...; ``python -m ttsim_jax.fit.synthetic_contacts``):
  :mod:`ttsim_jax.fit.synthetic_contacts`.
"""

import warnings

from ttsim_jax.errors import ConfigError
from ttsim_jax.files.checkpoint import CheckpointError
from ttsim_jax.fit.network_config import TrainConfig, load_train_config
from ttsim_jax.fit.network_evaluation import (COMPONENTS, DISTANCE_BANDS, ERROR_NAMES, band_label, calibrate_sigma,
                                              contact_errors, distance_bands, evaluate_by_band, evaluate_residual,
                                              predict)
from ttsim_jax.fit.network_stats import CALIBRATION_MODES
from ttsim_jax.fit.network_training import TRAIN_STATE_KIND, gaussian_nll, split_by_contact, train_residual
from ttsim_jax.fit.synthetic_contacts import (BALL_MASS, BALL_RADIUS, FACE_RADIUS, main, make_synthetic_contacts,
                                              racket_base_fn, recovery_experiment, sample_racket_inputs,
                                              standin_base_fn, true_residual)
from ttsim_jax.physics.network import ResidualConfig, ResidualModel

__all__ = [
    "BALL_MASS", "BALL_RADIUS", "CALIBRATION_MODES", "COMPONENTS", "DISTANCE_BANDS", "ERROR_NAMES", "FACE_RADIUS",
    "TRAIN_STATE_KIND", "CheckpointError", "ConfigError", "ResidualConfig", "ResidualModel", "TrainConfig",
    "band_label", "calibrate_sigma", "contact_errors", "distance_bands", "evaluate_by_band", "evaluate_residual",
    "gaussian_nll", "load_train_config", "make_synthetic_contacts", "predict", "racket_base_fn",
    "recovery_experiment", "sample_racket_inputs", "split_by_contact", "standin_base_fn", "train_residual",
    "true_residual",
]

warnings.warn("ttsim_jax.fit.residual is deprecated and will be removed in the next release: import from "
              "ttsim_jax.fit.network_training (training), ttsim_jax.fit.network_config (TrainConfig), "
              "ttsim_jax.fit.network_evaluation (evaluation, sigma calibration) or "
              "ttsim_jax.fit.synthetic_contacts (the synthetic set and the recovery experiment)",
              DeprecationWarning, stacklevel=2)

if __name__ == "__main__":
    main()
