"""A residual network's file: a :class:`~ttsim_jax.physics.network.ResidualModel` in a checkpoint
container (:mod:`ttsim_jax.files.checkpoint`) of kind ``"residual-model"``, conventionally ``*.ttres``.

The header holds the network's configuration and optional notes (e.g. the training report); the
payload holds the variables, the input and output statistics, the attenuation centres and
coefficients and the sigma calibration, bit-exactly. Format versions: 1 had no ``sigma_scale``;
2 (current) adds it. Version-1 files are still read, with ``sigma_scale`` = 1 (uncalibrated
sigmas) and a warning.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.errors import ConfigError
from ttsim_jax.files.checkpoint import CheckpointError, flatten_arrays, read_container, write_container
from ttsim_jax.physics.network import ResidualConfig, ResidualModel, model_shapes

MODEL_KIND = "residual-model"
# Model-file versions this code reads (version 1 predates ``sigma_scale``; it loads as 1).
READABLE_MODEL_VERSIONS = (1, 2)


def _config_from_header(d: Any, path) -> ResidualConfig:
    if not isinstance(d, dict):
        raise CheckpointError(f"{path}: header key 'config' is not an object: {d!r}")
    known = {f.name for f in dataclasses.fields(ResidualConfig)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise CheckpointError(f"{path}: header 'config' has unknown key(s) {unknown}")
    try:
        return ResidualConfig(**d)
    except (ConfigError, TypeError) as e:
        raise CheckpointError(f"{path}: header key 'config' is invalid: {e}") from None


def model_arrays(model: ResidualModel) -> dict:
    """The arrays of ``model`` as the file stores them: a nested dict of numpy arrays."""
    return dict(variables=jax.tree_util.tree_map(np.asarray, dict(model.variables)),
                x_min=np.asarray(model.x_min), x_max=np.asarray(model.x_max),
                y_mean=np.asarray(model.y_mean), y_scale=np.asarray(model.y_scale),
                centres=np.asarray(model.centres), beta_coef=np.asarray(model.beta_coef),
                sigma_scale=np.asarray(model.sigma_scale))


def model_from_arrays(arrays: dict, config: ResidualConfig, path="<arrays>", prefix="") -> ResidualModel:
    """Builds a :class:`ResidualModel` from nested numpy arrays, checking every key and shape.

    Arguments:
        arrays: nested dict as stored by :func:`save_residual`.
        config: the configuration the arrays must match.
        path, prefix: used in error messages (file name, key prefix).

    Returns:
        The model (arrays converted bit-exactly). Raises :class:`CheckpointError` naming the file
        and key of a missing, unexpected or wrongly shaped array.
    """
    expected = flatten_arrays(model_shapes(config))
    got = flatten_arrays(arrays) if isinstance(arrays, dict) else {}
    for key in sorted(expected):
        if key not in got:
            raise CheckpointError(f"{path}: missing array {prefix + key!r} (config {config.to_dict()})")
        shape = tuple(np.shape(got[key]))
        if shape != tuple(expected[key]):
            raise CheckpointError(f"{path}: key {prefix + key!r} has shape {shape}, expected {tuple(expected[key])} "
                                  f"for n_inputs={config.n_inputs}, trunk={list(config.trunk)}, "
                                  f"head_width={config.head_width}, n_clusters={config.n_clusters}")
        if not np.issubdtype(np.asarray(got[key]).dtype, np.floating):
            raise CheckpointError(f"{path}: key {prefix + key!r} has dtype {np.asarray(got[key]).dtype}, "
                                  "expected floating")
    extra = sorted(set(got) - set(expected))
    if extra:
        raise CheckpointError(f"{path}: unexpected array(s) {[prefix + k for k in extra]} for this config")
    to_jnp = lambda a: jnp.asarray(np.asarray(a))  # noqa: E731
    return ResidualModel(
        variables=jax.tree_util.tree_map(to_jnp, arrays["variables"]),
        x_min=to_jnp(arrays["x_min"]), x_max=to_jnp(arrays["x_max"]),
        y_mean=to_jnp(arrays["y_mean"]), y_scale=to_jnp(arrays["y_scale"]),
        centres=to_jnp(arrays["centres"]), beta_coef=to_jnp(arrays["beta_coef"]),
        sigma_scale=to_jnp(arrays["sigma_scale"]), config=config,
    )


def save_residual(path, model: ResidualModel, metadata: dict | None = None) -> None:
    """Saves a residual model to one file, atomically (see the module docstring for the format).

    Arguments:
        path: destination file (conventionally ``*.ttres``).
        model: the model.
        metadata: optional JSON-serialisable notes (e.g. the training report) kept in the header.
    """
    header = dict(config=model.config.to_dict(), metadata=metadata or {})
    write_container(path, MODEL_KIND, header, model_arrays(model))


def load_residual(path, expected_config: ResidualConfig | None = None) -> ResidualModel:
    """Loads a residual model saved by :func:`save_residual`, bit-exactly.

    Arguments:
        path: the file.
        expected_config: if given, the stored configuration must equal it.

    Returns:
        The :class:`ResidualModel`. Raises :class:`CheckpointError` naming the file and key for a
        truncated, corrupted, wrong-version or mismatched file. A version-1 file (written before
        sigma calibration existed) loads with ``sigma_scale`` = 1 and a ``UserWarning``.
    """
    header, arrays = read_container(path, MODEL_KIND, READABLE_MODEL_VERSIONS)
    if header["format_version"] == 1:
        if isinstance(arrays, dict) and "sigma_scale" in arrays:
            raise CheckpointError(f"{path}: a version-1 file must not hold 'sigma_scale' (corrupted header)")
        warnings.warn(f"{path}: residual checkpoint format version 1 has no sigma calibration; "
                      "loading it with sigma_scale = 1 (predicted sigmas uncalibrated). Retrain to calibrate.",
                      UserWarning, stacklevel=2)
        arrays = dict(arrays, sigma_scale=np.ones((6,), np.float32))
    if "config" not in header:
        raise CheckpointError(f"{path}: header lacks key 'config'")
    config = _config_from_header(header["config"], path)
    if expected_config is not None and config != expected_config:
        diff = {k: (v, getattr(expected_config, k)) for k, v in dataclasses.asdict(config).items()
                if v != getattr(expected_config, k)}
        raise CheckpointError(f"{path}: key 'config' does not match the expected configuration "
                              f"(stored, expected): {diff}")
    return model_from_arrays(arrays, config, path)


def checkpoint_metadata(path) -> dict:
    """The ``metadata`` stored by :func:`save_residual` (verified like :func:`load_residual`)."""
    header, _ = read_container(path, MODEL_KIND, READABLE_MODEL_VERSIONS)
    return header.get("metadata", {})
