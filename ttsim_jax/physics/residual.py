"""The racket contact's residual neural network, its attenuation and its checkpoint format.

The network corrects the base racket model in the racket frame (x = face normal, y and z
tangential). Its input is x = (v~, w~, d) in R^8: the ball's velocity relative to the face at the
contact point, its spin relative to the racket's, and the contact position d = (d_y, d_z) on the
face; the Dürr 2026 variant drops d (6 inputs). It predicts velocity and spin residuals
(dv, dw) and per-component standard deviations (sigma_v, sigma_w). The corrected prediction is

    v+ = v+_base + beta(v~, w~) dv,      w+ = w+_base + beta(v~, w~) dw,

with beta = clip(a exp(-b dist) - c, 0, 1) and dist the distance of the scaled (v~, w~) to the
nearest k-means centre of the training inputs, so the correction fades out away from the data.

Implementation choices beyond the paper (each documented where it is made):

* Output standardisation: the heads predict residuals in units of the training targets' standard
  deviation (``y_mean``, ``y_scale`` in :class:`ResidualModel`). Spin residuals are ~100x larger
  than velocity residuals; without it the last layer would need weights ~100x larger. The Gaussian
  NLL is unchanged by it up to a constant, so training is the paper's objective.
* log sigma is soft-clamped to +-``log_sigma_bound`` (in standardised units) with a tanh, so
  exp() stays finite and the NLL cannot collapse on duplicated points; gradients never vanish.
* Everything here is inference-mode (batch-norm running statistics, no dropout), hence row-wise:
  this is what makes :func:`gathered_residual`'s gather/scatter exact. Training replaces the
  running averages (an exponential average over the last few mini-batches, i.e. over the last
  ~10 batches of 16 contacts) by the exact population statistics of the whole training split
  (:func:`population_batch_stats`), which do not depend on the order of the batches.
* Sigma calibration: the predicted sigmas are multiplied by ``sigma_scale`` (6,), fitted on the
  validation split after training so that ~68.3 % of held-out errors fall inside one sigma
  (:func:`calibration_scale`). The Gaussian NLL alone leaves them over- or under-confident
  (early stopping, weight decay and dropout all bias them).

Checkpoint file (``save_residual`` / ``load_residual``): one file,

    b"TTSIM-RESIDUAL\\n" + <JSON header, one line> + b"\\n" + <msgpack payload>

The header holds the format version, the configuration, the payload's length and SHA-256, and
every array's shape and dtype; the payload (``flax.serialization`` msgpack) holds the arrays
bit-exactly. Format versions: 1 had no ``sigma_scale``; 2 (current) adds it. Version-1 model
files are still read, with ``sigma_scale`` = 1 (uncalibrated sigmas) and a warning; training-state
files must be of the current version.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import tomllib
import warnings
from functools import partial
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization, struct

from ttsim_jax.io_atomic import atomic_write

# The paper's authors' attenuation coefficients (beta = 1 for dist <= 0.150, 0 for dist >= 0.383).
PAPER_BETA = (7.282, 12.899, 0.052)

CHECKPOINT_MAGIC = b"TTSIM-RESIDUAL\n"
CHECKPOINT_VERSION = 2
# Model-file versions this code reads (version 1 predates ``sigma_scale``; it loads as 1).
READABLE_MODEL_VERSIONS = (1, 2)
# The fraction of a Gaussian inside one standard deviation, erf(1 / sqrt(2)).
ONE_SIGMA_COVERAGE = 0.6826894921370859

# Width of the (v~, w~) part of the input, on which the attenuation depends.
N_ATTENUATION_INPUTS = 6


class CheckpointError(ValueError):
    """A residual checkpoint that cannot be read: wrong magic, version, truncated, corrupted, or
    not matching its configuration. The message names the file and the offending key."""


class ConfigError(ValueError):
    """A residual configuration with a missing, unknown or invalid key."""


@dataclasses.dataclass(frozen=True)
class ResidualConfig:
    """Architecture of the residual network and the default attenuation (hashable, static).

    Attributes:
        n_inputs: 8 for x = (v~, w~, d) (the paper) or 6 for x = (v~, w~) (Dürr 2026).
        trunk: widths of the shared trunk's Dense -> BatchNorm -> ReLU layers.
        dropout: dropout rate applied after trunk layer ``dropout_after``.
        dropout_after: 1-based index of the trunk layer followed by dropout (the paper's: 2).
        head_width: hidden width of each of the four heads (Dense -> SiLU -> Dense(3)).
        n_clusters: k-means centres of the training (v~, w~) for the attenuation. The paper's
            1000; small test configs use fewer (it must not exceed the training contacts).
        beta_a, beta_b, beta_c: default attenuation coefficients (the authors'); training may
            recalibrate ``beta_b`` and stores the coefficients used in the model.
        bn_momentum: batch-norm running-average momentum in Flax's convention (0.9 equals
            PyTorch's default momentum 0.1, which the authors' code uses).
        log_sigma_bound: soft bound on |log sigma| in standardised units (see module docstring).
    """

    n_inputs: int = 8
    trunk: tuple[int, ...] = (64, 64, 32)
    dropout: float = 0.2
    dropout_after: int = 2
    head_width: int = 32
    n_clusters: int = 1000
    beta_a: float = PAPER_BETA[0]
    beta_b: float = PAPER_BETA[1]
    beta_c: float = PAPER_BETA[2]
    bn_momentum: float = 0.9
    log_sigma_bound: float = 7.0

    def __post_init__(self):
        object.__setattr__(self, "trunk", tuple(int(w) for w in self.trunk))
        problems = _config_problems(self)
        if problems:
            raise ConfigError("invalid ResidualConfig: " + "; ".join(problems))

    def to_dict(self) -> dict:
        """JSON-friendly dict of the fields."""
        d = dataclasses.asdict(self)
        d["trunk"] = list(self.trunk)
        return d


def _config_problems(cfg: ResidualConfig) -> list[str]:
    out = []
    if cfg.n_inputs not in (6, 8):
        out.append(f"n_inputs = {cfg.n_inputs!r}: must be 8 (v~, w~, d) or 6 (v~, w~)")
    if len(cfg.trunk) < 1 or any(w < 1 for w in cfg.trunk):
        out.append(f"trunk = {list(cfg.trunk)!r}: needs at least one positive width")
    if not 0.0 <= cfg.dropout < 1.0:
        out.append(f"dropout = {cfg.dropout!r}: must be in [0, 1)")
    if not 0 <= cfg.dropout_after <= len(cfg.trunk):
        out.append(f"dropout_after = {cfg.dropout_after!r}: must be in [0, {len(cfg.trunk)}] (0 = none)")
    if cfg.head_width < 1:
        out.append(f"head_width = {cfg.head_width!r}: must be >= 1")
    if cfg.n_clusters < 1:
        out.append(f"n_clusters = {cfg.n_clusters!r}: must be >= 1")
    if not (cfg.beta_a > 0 and cfg.beta_b > 0 and cfg.beta_c >= 0):
        out.append(f"beta (a, b, c) = ({cfg.beta_a}, {cfg.beta_b}, {cfg.beta_c}): need a > 0, b > 0, c >= 0")
    if not 0.0 < cfg.bn_momentum < 1.0:
        out.append(f"bn_momentum = {cfg.bn_momentum!r}: must be in (0, 1)")
    if not cfg.log_sigma_bound > 0:
        out.append(f"log_sigma_bound = {cfg.log_sigma_bound!r}: must be > 0")
    return out


# TOML layout: [model] and [attenuation] map onto ResidualConfig; [training] belongs to
# ttsim_jax.fit.residual.TrainConfig and is checked there.
_MODEL_KEYS = {
    "n_inputs": ("n_inputs", True),
    "trunk": ("trunk", True),
    "dropout": ("dropout", True),
    "dropout_after": ("dropout_after", False),
    "head_width": ("head_width", True),
    "n_clusters": ("n_clusters", True),
    "bn_momentum": ("bn_momentum", False),
    "log_sigma_bound": ("log_sigma_bound", False),
}
_ATTENUATION_KEYS = {"a": ("beta_a", True), "b": ("beta_b", True), "c": ("beta_c", True)}
CONFIG_TABLES = ("model", "attenuation", "training")


def read_toml(path) -> dict:
    """Parses a TOML file, naming the file in any error."""
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such configuration file") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: not valid TOML: {e}") from None


def _take_table(doc: dict, table: str, spec: dict, path) -> dict:
    if table not in doc:
        raise ConfigError(f"{path}: missing table [{table}]")
    got = doc[table]
    if not isinstance(got, dict):
        raise ConfigError(f"{path}: [{table}] must be a table, got {got!r}")
    unknown = sorted(set(got) - set(spec))
    if unknown:
        raise ConfigError(f"{path}: unknown key(s) {unknown} in [{table}]; known: {sorted(spec)}")
    missing = sorted(k for k, (_, required) in spec.items() if required and k not in got)
    if missing:
        raise ConfigError(f"{path}: missing key(s) {missing} in [{table}]")
    return {field: got[key] for key, (field, _) in spec.items() if key in got}


def residual_config_from_toml(doc: dict, path="<config>") -> ResidualConfig:
    """Builds a :class:`ResidualConfig` from a parsed TOML document ([model], [attenuation]).

    Arguments:
        doc: the parsed document.
        path: the file name used in error messages.

    Returns:
        The configuration. Raises :class:`ConfigError` naming the file and key on a missing,
        unknown or invalid key.
    """
    unknown_tables = sorted(set(doc) - set(CONFIG_TABLES))
    if unknown_tables:
        raise ConfigError(f"{path}: unknown table(s) {unknown_tables}; known: {list(CONFIG_TABLES)}")
    fields = _take_table(doc, "model", _MODEL_KEYS, path)
    fields.update(_take_table(doc, "attenuation", _ATTENUATION_KEYS, path))
    types = {"n_inputs": int, "dropout_after": int, "head_width": int, "n_clusters": int}
    for name, value in fields.items():
        table = "attenuation" if name.startswith("beta_") else "model"
        key = name[5:] if name.startswith("beta_") else name
        if name == "trunk":
            if not isinstance(value, list) or not all(isinstance(w, int) and not isinstance(w, bool) for w in value):
                raise ConfigError(f"{path}: [model] trunk = {value!r}: must be a list of integers")
        elif types.get(name) is int:
            if not isinstance(value, int) or isinstance(value, bool):
                raise ConfigError(f"{path}: [{table}] {key} = {value!r}: must be an integer")
        elif not isinstance(value, (int, float)) or isinstance(value, bool):
            raise ConfigError(f"{path}: [{table}] {key} = {value!r}: must be a number")
    try:
        return ResidualConfig(**fields)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None


def load_residual_config(path) -> ResidualConfig:
    """Reads the network architecture and attenuation from a TOML config (configs/residual/).

    Arguments:
        path: TOML file with tables [model], [attenuation] and optionally [training] (the latter
            is read by :func:`ttsim_jax.fit.residual.load_train_config`).

    Returns:
        The :class:`ResidualConfig`. Raises :class:`ConfigError` naming the file and key for a
        missing, unknown or invalid key.
    """
    return residual_config_from_toml(read_toml(path), path)


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


# ----------------------------------------------------------------------------------------------
# Network


class ResidualNet(nn.Module):
    """Shared trunk and four heads; all outputs in standardised units.

    Attributes:
        config: the architecture.
    """

    config: ResidualConfig

    @nn.compact
    def __call__(self, x_scaled, train: bool):
        """Evaluates the network.

        Arguments:
            x_scaled: (N, n_inputs) min-max scaled inputs.
            train: batch statistics of this batch and dropout (needs the 'dropout' rng and a
                mutable 'batch_stats') when True; running statistics and no dropout when False.

        Returns:
            (dv, dw, log_sigma_v, log_sigma_w), each (N, 3), in standardised units; the log
            sigmas are already soft-clamped.
        """
        cfg = self.config
        h = x_scaled
        for i, width in enumerate(cfg.trunk):
            h = nn.Dense(width, name=f"trunk_{i}")(h)
            h = nn.BatchNorm(use_running_average=not train, momentum=cfg.bn_momentum, epsilon=1e-5,
                             name=f"bn_{i}")(h)
            h = nn.relu(h)
            if i + 1 == cfg.dropout_after and cfg.dropout > 0.0:
                h = nn.Dropout(cfg.dropout, deterministic=not train)(h)

        def head(name):
            z = nn.silu(nn.Dense(cfg.head_width, name=f"{name}_hidden")(h))
            return nn.Dense(3, name=f"{name}_out")(z)

        bound = cfg.log_sigma_bound
        soft = lambda s: bound * jnp.tanh(s / bound)  # noqa: E731
        return head("dv"), head("dw"), soft(head("log_sigma_v")), soft(head("log_sigma_w"))


def init_variables(config: ResidualConfig, key) -> dict:
    """Fresh network variables {'params', 'batch_stats'} for ``config``.

    Arguments:
        config: the architecture.
        key: PRNG key.

    Returns:
        The variables dict.
    """
    return dict(_init_variables(key, config))


@partial(jax.jit, static_argnames=("config",))
def _init_variables(key, config: ResidualConfig):
    # jitted: initialising op by op dispatches dozens of small computations
    x = jnp.zeros((2, config.n_inputs), jnp.float32)
    return ResidualNet(config).init({"params": key}, x, train=False)


def variable_shapes(config: ResidualConfig) -> dict:
    """Shapes of the network variables for ``config``, without computing them."""
    abstract = jax.eval_shape(lambda k: init_variables(config, k), jax.random.key(0))
    return jax.tree_util.tree_map(lambda a: tuple(a.shape), abstract)


# ----------------------------------------------------------------------------------------------
# Model pytree


@struct.dataclass
class ResidualModel:
    """A trained residual network with everything needed to evaluate it (a pytree).

    Swapping one model for another of the same ``config`` never recompiles: every array is a leaf,
    only ``config`` is static.

    Attributes:
        variables: {'params': ..., 'batch_stats': ...} of :class:`ResidualNet`.
        x_min, x_max: (n_inputs,) min-max statistics of the training inputs; the network sees
            (x - x_min) / (x_max - x_min), i.e. [0, 1] on the training set.
        y_mean, y_scale: (6,) mean and standard deviation of the training targets (dv, dw) in
            physical units; the heads predict (target - y_mean) / y_scale.
        centres: (n_clusters, 6) k-means centres of the scaled training (v~, w~).
        beta_coef: (3,) attenuation coefficients (a, b, c) as fitted / validated in training.
        sigma_scale: (6,) calibration factors of the predicted sigmas (v_x .. w_z), fitted on
            the validation split after training (1 = uncalibrated).
        config: the architecture (static).
    """

    variables: Any
    x_min: jnp.ndarray
    x_max: jnp.ndarray
    y_mean: jnp.ndarray
    y_scale: jnp.ndarray
    centres: jnp.ndarray
    beta_coef: jnp.ndarray
    sigma_scale: jnp.ndarray
    config: ResidualConfig = struct.field(pytree_node=False)


def model_shapes(config: ResidualConfig) -> dict:
    """Expected shapes of every array of a :class:`ResidualModel` with ``config``."""
    n = config.n_inputs
    return dict(
        variables=variable_shapes(config),
        x_min=(n,), x_max=(n,), y_mean=(6,), y_scale=(6,),
        centres=(config.n_clusters, N_ATTENUATION_INPUTS), beta_coef=(3,), sigma_scale=(6,),
    )


def init_model(config: ResidualConfig, key) -> ResidualModel:
    """An untrained model: fresh variables, identity-like scaling, centres at 0.5.

    Arguments:
        config: the architecture.
        key: PRNG key for the variables.

    Returns:
        A :class:`ResidualModel` (useful for tests and as a shape template).
    """
    n = config.n_inputs
    return ResidualModel(
        variables=init_variables(config, key),
        x_min=jnp.zeros((n,), jnp.float32), x_max=jnp.ones((n,), jnp.float32),
        y_mean=jnp.zeros((6,), jnp.float32), y_scale=jnp.ones((6,), jnp.float32),
        centres=jnp.full((config.n_clusters, N_ATTENUATION_INPUTS), 0.5, jnp.float32),
        beta_coef=jnp.asarray([config.beta_a, config.beta_b, config.beta_c], jnp.float32),
        sigma_scale=jnp.ones((6,), jnp.float32),
        config=config,
    )


def _check_x(model: ResidualModel, x, where: str):
    n = model.config.n_inputs
    if x.ndim != 2 or x.shape[1] != n:
        kind = "(v~, w~, d)" if n == 8 else "(v~, w~)"
        raise ValueError(f"{where}: x has shape {tuple(x.shape)}; the model expects (N, {n}) inputs {kind}")


def scale_inputs(model: ResidualModel, x):
    """Min-max scales raw inputs (N, n_inputs) with the training statistics (not clipped, so
    out-of-range inputs stay visible to the attenuation)."""
    span = jnp.maximum(model.x_max - model.x_min, 1e-12)
    return (x - model.x_min) / span


def nearest_distance(points, centres):
    """Euclidean distance (N,) from each point (N, D) to its nearest centre (K, D).

    Uses |p|^2 - 2 p.c + |c|^2 (memory O(N K), not O(N K D)); the clamp keeps sqrt and its
    gradient finite where rounding makes the squared distance slightly negative.
    """
    d2 = (jnp.sum(points * points, axis=1, keepdims=True) - 2.0 * points @ centres.T
          + jnp.sum(centres * centres, axis=1)[None, :])
    return jnp.sqrt(jnp.maximum(jnp.min(d2, axis=1), 1e-12))


def beta_from_distance(dist, beta_coef):
    """beta = clip(a exp(-b dist) - c, 0, 1) for coefficients (a, b, c)."""
    a, b, c = beta_coef[0], beta_coef[1], beta_coef[2]
    return jnp.clip(a * jnp.exp(-b * dist) - c, 0.0, 1.0)


def attenuation(model: ResidualModel, x_scaled):
    """Distance-based attenuation beta of the residual.

    Arguments:
        model: the residual model (centres and beta coefficients).
        x_scaled: (N, >= 6) scaled inputs; only the first 6, (v~, w~), are used, as in the paper.

    Returns:
        (N,) beta in [0, 1]: 1 near the training data, 0 far from it.
    """
    z = x_scaled[:, :N_ATTENUATION_INPUTS]
    return beta_from_distance(nearest_distance(z, model.centres.astype(z.dtype)), model.beta_coef)


def network_outputs(model: ResidualModel, x_scaled):
    """Raw inference-mode outputs in physical units: (dv, dw, sigma_v, sigma_w), each (N, 3),
    without attenuation; the sigmas include the calibration ``sigma_scale``."""
    dv_n, dw_n, ls_v, ls_w = ResidualNet(model.config).apply(model.variables, x_scaled, train=False)
    mean, scale = model.y_mean, model.y_scale
    s_scale = scale * model.sigma_scale
    return (mean[:3] + scale[:3] * dv_n, mean[3:] + scale[3:] * dw_n,
            s_scale[:3] * jnp.exp(ls_v), s_scale[3:] * jnp.exp(ls_w))


def residual_outputs(model: ResidualModel, x, attenuate: bool = True) -> dict:
    """Evaluates the residual network on every row (inference mode).

    Arguments:
        model: the residual model.
        x: (N, n_inputs) raw racket-frame inputs (v~, w~[, d]).
        attenuate: static Python flag; False returns the network's raw residuals.

    Returns:
        dict with ``dv``, ``dw`` (N, 3): the residuals to add to the base model's racket-frame
        (v+, w+), already multiplied by ``beta`` when ``attenuate``; ``sigma_v``, ``sigma_w``
        (N, 3): the predicted standard deviations of the raw residuals (not attenuated);
        ``beta`` (N,).
    """
    x = jnp.asarray(x)
    _check_x(model, x, "residual_outputs")
    xs = scale_inputs(model, x)
    dv, dw, sv, sw = network_outputs(model, xs)
    beta = attenuation(model, xs)
    if attenuate:
        dv, dw = beta[:, None] * dv, beta[:, None] * dw
    return dict(dv=dv, dw=dw, sigma_v=sv, sigma_w=sw, beta=beta)


def sampled_residual(model, x, eps):
    """Attenuated outputs, with sigma * eps added to the raw residuals first when eps is given."""
    out = residual_outputs(model, x, attenuate=False)
    if eps is not None:
        out["dv"] = out["dv"] + out["sigma_v"] * eps[:, :3]
        out["dw"] = out["dw"] + out["sigma_w"] * eps[:, 3:]
    b = out["beta"][:, None]
    out["dv"], out["dw"] = b * out["dv"], b * out["dw"]
    return out


def gathered_residual(model: ResidualModel, x, mask, capacity: int, key=None, sample: bool = False) -> dict:
    """Residuals for the masked rows of a batch, evaluating the network on a fixed-size buffer.

    The rows where ``mask`` is True are gathered into a buffer of ``capacity`` rows, the network
    runs on the buffer only, and the results are scattered back. This is exact because inference
    mode is row-wise (batch norm uses running statistics). A ``lax.switch`` at batch level picks:
    no masked row -> zeros without running the network; up to ``capacity`` -> the buffer; more ->
    the whole batch (correct, at full cost). Under ``jax.vmap`` the switch evaluates every branch,
    so call this on the batch, not inside a vmapped per-ball function. Differentiable (no
    while_loop).

    Arguments:
        model: the residual model.
        x: (B, n_inputs) raw racket-frame inputs.
        mask: (B,) bool, the balls touching a racket this step.
        capacity: static buffer size (a Python int >= 1).
        key: PRNG key, required when ``sample``.
        sample: static flag; add sigma * N(0, 1) to the raw residuals (domain randomisation)
            before attenuation, so the noise fades with beta like the residual. The noise is
            drawn per batch row, so it does not depend on which branch ran.

    Returns:
        dict like :func:`residual_outputs`: ``dv``, ``dw`` (B, 3) already multiplied by ``beta``
        (and including the noise when ``sample``), ``sigma_v``, ``sigma_w`` (B, 3), ``beta``
        (B,); all zeros where ``mask`` is False.
    """
    x = jnp.asarray(x)
    mask = jnp.asarray(mask)
    _check_x(model, x, "gathered_residual")
    b = x.shape[0]
    if mask.shape != (b,) or mask.dtype != jnp.bool_:
        raise ValueError(f"gathered_residual: mask must be a ({b},) bool array, got {mask.shape} {mask.dtype}")
    if not isinstance(capacity, int) or capacity < 1:
        raise ValueError(f"gathered_residual: capacity must be a Python int >= 1, got {capacity!r}")
    if sample and key is None:
        raise ValueError("gathered_residual: sample=True needs a PRNG key")
    capacity = min(capacity, b)
    eps = jax.random.normal(key, (b, 6), x.dtype) if sample else None
    zeros = dict(dv=jnp.zeros((b, 3), x.dtype), dw=jnp.zeros((b, 3), x.dtype),
                 sigma_v=jnp.zeros((b, 3), x.dtype), sigma_w=jnp.zeros((b, 3), x.dtype),
                 beta=jnp.zeros((b,), x.dtype))

    def none(_):
        return zeros

    def buffered(_):
        # Out-of-range fill index b: the gather clips it (any row will do, its result is
        # dropped) and the scatter drops it.
        idx = jnp.nonzero(mask, size=capacity, fill_value=b)[0]
        rows = jnp.take(x, idx, axis=0, mode="clip")
        noise = None if eps is None else jnp.take(eps, idx, axis=0, mode="clip")
        out = sampled_residual(model, rows, noise)
        return {k: zeros[k].at[idx].set(v.astype(x.dtype), mode="drop") for k, v in out.items()}

    def full(_):
        out = sampled_residual(model, x, eps)
        m = mask[:, None]
        return {k: jnp.where(m if v.ndim == 2 else mask, v.astype(x.dtype), 0.0) for k, v in out.items()}

    count = jnp.sum(mask)
    branch = (count > 0).astype(jnp.int32) + (count > capacity).astype(jnp.int32)
    return jax.lax.switch(branch, (none, buffered, full), None)


# ----------------------------------------------------------------------------------------------
# Batch-norm statistics and sigma calibration (after training)


@partial(jax.jit, static_argnames=("config",))
def _population_stats(params, x_scaled, weights, config: ResidualConfig):
    h = x_scaled
    stats = {}
    total = jnp.sum(weights)
    for i, _ in enumerate(config.trunk):
        dense = params[f"trunk_{i}"]
        h = h @ dense["kernel"] + dense["bias"]
        # Two-pass (centred) moments: no cancellation when |mean| >> std.
        mean = jnp.sum(weights[:, None] * h, axis=0) / total
        var = jnp.sum(weights[:, None] * (h - mean) ** 2, axis=0) / total
        stats[f"bn_{i}"] = {"mean": mean, "var": var}
        bn = params[f"bn_{i}"]
        h = (h - mean) * jax.lax.rsqrt(var + 1e-5) * bn["scale"] + bn["bias"]  # as flax.linen.BatchNorm
        h = jax.nn.relu(h)
        # dropout is the identity in inference mode
    return stats


def population_batch_stats(variables, config: ResidualConfig, x_scaled, weights=None) -> dict:
    """Exact batch-norm statistics of a data set, replacing the running averages.

    Training keeps an exponential moving average of mini-batch statistics, which reflects the
    last few batches (and their order). This recomputes, layer by layer in inference mode (no
    dropout, earlier layers already normalised with their recomputed statistics), the mean and
    the (biased, as Flax's) variance of every batch-norm input over the whole of ``x_scaled``:
    one pass over the data, independent of any order. With them, inference mode on a data set
    reproduces training mode with the whole set as one batch (dropout off).

    Arguments:
        variables: {'params', 'batch_stats'} of :class:`ResidualNet` (batch_stats is replaced).
        config: the architecture.
        x_scaled: (N, n_inputs) min-max scaled inputs (normally the whole training split).
        weights: optional (N,) non-negative row weights (e.g. 0 for padding rows).

    Returns:
        New variables {'params', 'batch_stats'} with the population statistics (dtype of the
        old statistics).
    """
    x_scaled = jnp.asarray(x_scaled)
    if x_scaled.ndim != 2 or x_scaled.shape[1] != config.n_inputs or x_scaled.shape[0] < 1:
        raise ValueError(f"population_batch_stats: x_scaled has shape {tuple(x_scaled.shape)}, "
                         f"expected (N >= 1, {config.n_inputs})")
    w = jnp.ones((x_scaled.shape[0],), x_scaled.dtype) if weights is None else jnp.asarray(weights, x_scaled.dtype)
    params = variables["params"]
    stats = _population_stats(params, x_scaled, w, config)
    old = variables["batch_stats"]
    stats = {k: {n: v.astype(jnp.asarray(old[k][n]).dtype) for n, v in d.items()} for k, d in stats.items()}
    return {"params": params, "batch_stats": stats}


def calibration_scale(abs_error, sigma, groups=None, target=ONE_SIGMA_COVERAGE, floor=1e-6):
    """Factors that make a fraction ``target`` of the errors fall inside one scaled sigma.

    For each group of components, the factor s is the ``target`` quantile of |error| / sigma
    over all rows and components of the group, so that |error| <= s sigma for that fraction of
    them (the empirical coverage; it does not assume Gaussian errors).

    Arguments:
        abs_error: (M, 6) absolute errors of the (corrected) prediction on held-out data.
        sigma: (M, 6) the predicted sigmas (uncalibrated).
        groups: (6,) group label of each component (default: each its own group); e.g.
            (0, 0, 0, 1, 1, 1) for one factor for velocity and one for spin.
        target: wanted coverage (default: a Gaussian's one-sigma mass, 0.6827).
        floor: lower bound of a factor (keeps sigmas positive).

    Returns:
        (6,) float64 factors.
    """
    ratio = np.asarray(abs_error, np.float64) / np.maximum(np.asarray(sigma, np.float64), 1e-30)
    if ratio.ndim != 2 or ratio.shape[1] != 6 or ratio.shape[0] < 1:
        raise ValueError(f"calibration_scale: need (M >= 1, 6) errors and sigmas, got {ratio.shape}")
    groups = np.arange(6) if groups is None else np.asarray(groups)
    out = np.ones(6)
    for g in np.unique(groups):
        cols = groups == g
        out[cols] = max(float(np.quantile(ratio[:, cols], target)), floor)
    return out


# ----------------------------------------------------------------------------------------------
# k-means


@partial(jax.jit, static_argnames=("k", "iters"))
def kmeans(points, k: int, key, iters: int = 50):
    """k-means clustering: k-means++ initialisation, then Lloyd iterations.

    Arguments:
        points: (N, D) points, N >= k.
        k: number of centres (static).
        key: PRNG key for the initialisation.
        iters: Lloyd iterations (static).

    Returns:
        (k, D) centres. A centre that loses all its points keeps its position.
    """
    points = jnp.asarray(points)
    n = points.shape[0]
    if n < k:
        raise ValueError(f"kmeans: {n} points cannot make {k} clusters")
    k0, kseq = jax.random.split(key)

    def sqdist(c):
        return jnp.sum((points - c) ** 2, axis=1)

    first = points[jax.random.randint(k0, (), 0, n)]
    centres = jnp.zeros((k, points.shape[1]), points.dtype).at[0].set(first)

    def pp_step(i, carry):
        centres, d2 = carry
        # k-means++: the next centre is drawn with probability proportional to the squared
        # distance to the nearest chosen centre; the tiny floor keeps duplicates drawable.
        j = jax.random.categorical(jax.random.fold_in(kseq, i), jnp.log(d2 + 1e-20))
        c = points[j]
        return centres.at[i].set(c), jnp.minimum(d2, sqdist(c))

    centres, _ = jax.lax.fori_loop(1, k, pp_step, (centres, sqdist(first)))

    def lloyd(_, centres):
        d2 = (jnp.sum(points * points, axis=1, keepdims=True) - 2.0 * points @ centres.T
              + jnp.sum(centres * centres, axis=1)[None, :])
        assign = jnp.argmin(d2, axis=1)
        sums = jax.ops.segment_sum(points, assign, num_segments=k)
        counts = jax.ops.segment_sum(jnp.ones((n,), points.dtype), assign, num_segments=k)
        return jnp.where(counts[:, None] > 0, sums / jnp.maximum(counts, 1.0)[:, None], centres)

    return jax.lax.fori_loop(0, iters, lloyd, centres)


def calibrate_beta(dist_heldout, a=PAPER_BETA[0], b=PAPER_BETA[1], c=PAPER_BETA[2], quantile=0.99):
    """Validates the attenuation on held-out data and rescales its distance if needed.

    The paper's curve gives full trust (beta = 1) up to dist_1 = ln(a / (1 + c)) / b (0.150 for
    the authors' numbers), tuned to their data with 1000 centres. Distances to the nearest centre
    grow with fewer centres or sparser data, so a held-out contact from the training distribution
    could then be attenuated. Held-out data are in-distribution, so the residual should be fully
    trusted on (nearly) all of them: if the ``quantile`` of held-out distances exceeds dist_1, b
    is lowered so that dist_1 equals that quantile (the curve's shape, i.e. the ratio of its zero
    to its full-trust distance, is kept). Otherwise the coefficients pass unchanged.

    Arguments:
        dist_heldout: (M,) distances of held-out (validation) inputs to the nearest centre.
        a, b, c: the coefficients to validate.
        quantile: the fraction of held-out contacts that must get beta = 1.

    Returns:
        (coefficients (a, b', c) as floats, info dict with the distance quantile, the full-trust
        and zero distances before and after, and whether b was changed).
    """
    dist = np.asarray(dist_heldout, np.float64)
    dq = float(np.quantile(dist, quantile))
    d_one = math.log(a / (1.0 + c)) / b
    new_b = b if dq <= d_one else math.log(a / (1.0 + c)) / dq
    beta_old = np.clip(a * np.exp(-b * dist) - c, 0.0, 1.0)
    info = dict(distance_quantile=dq, quantile=quantile, full_trust_distance_before=d_one,
                full_trust_distance=math.log(a / (1.0 + c)) / new_b,
                zero_distance=math.log(a / c) / new_b if c > 0 else math.inf,
                rescaled=bool(new_b != b), mean_beta_heldout_before=float(beta_old.mean()))
    return (float(a), float(new_b), float(c)), info


# ----------------------------------------------------------------------------------------------
# Checkpoints


def _flatten(tree, prefix="") -> dict:
    out = {}
    for k, v in tree.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "/"))
        else:
            out[key] = v
    return out


def _model_arrays(model: ResidualModel) -> dict:
    return dict(variables=jax.tree_util.tree_map(np.asarray, dict(model.variables)),
                x_min=np.asarray(model.x_min), x_max=np.asarray(model.x_max),
                y_mean=np.asarray(model.y_mean), y_scale=np.asarray(model.y_scale),
                centres=np.asarray(model.centres), beta_coef=np.asarray(model.beta_coef),
                sigma_scale=np.asarray(model.sigma_scale))


def _to_plain(tree):
    """Nested dicts of numpy arrays (FrozenDicts and jax arrays turned plain)."""
    if hasattr(tree, "items"):
        return {str(k): _to_plain(v) for k, v in tree.items()}
    return np.asarray(tree)


def _check_finite(path, flat: dict) -> None:
    """Refuses non-finite floating arrays: a checkpoint holding NaN or inf weights is useless."""
    for k, v in flat.items():
        a = np.asarray(v)
        if np.issubdtype(a.dtype, np.floating) and not np.isfinite(a).all():
            first = np.unravel_index(int(np.flatnonzero(~np.isfinite(a))[0]), a.shape) if a.ndim else ()
            raise CheckpointError(f"{path}: key {k!r} holds non-finite values (first {a[first]} at index "
                                  f"{tuple(int(i) for i in first)})")


def write_container(path, kind: str, header: dict, arrays: dict) -> None:
    """Writes a checkpoint container (magic, JSON header, msgpack payload) atomically.

    Arguments:
        path: destination file.
        kind: what the file holds ("residual-model", or a training state).
        header: JSON-serialisable metadata stored in the header.
        arrays: nested dict of arrays (the payload).
    """
    arrays = _to_plain(arrays)
    flat = _flatten(arrays)
    _check_finite(path, flat)  # before writing, so the previous file stays
    payload = serialization.msgpack_serialize(arrays)
    head = dict(header, format_version=CHECKPOINT_VERSION, kind=kind, payload_bytes=len(payload),
                payload_sha256=hashlib.sha256(payload).hexdigest(),
                arrays={k: [list(v.shape), str(v.dtype)] for k, v in flat.items()})
    line = json.dumps(head, sort_keys=True).encode()
    atomic_write(path, CHECKPOINT_MAGIC + line + b"\n" + payload)


def read_container(path, kind: str, versions=(CHECKPOINT_VERSION,)) -> tuple[dict, dict]:
    """Reads and verifies a checkpoint container written by :func:`write_container`.

    Arguments:
        path: the file.
        kind: the expected kind.
        versions: the format versions accepted (default: the current one only).

    Returns:
        (header, arrays). Raises :class:`CheckpointError` naming the file (and key) if it is
        missing, not a checkpoint, of another format version or kind, truncated or corrupted.
    """
    try:
        with open(path, "rb") as f:
            data = f.read()
    except FileNotFoundError:
        raise CheckpointError(f"{path}: no such checkpoint file") from None
    if not data.startswith(CHECKPOINT_MAGIC):
        raise CheckpointError(f"{path}: not a ttsim residual checkpoint (bad magic bytes; truncated or another format)")
    end = data.find(b"\n", len(CHECKPOINT_MAGIC))
    if end < 0:
        raise CheckpointError(f"{path}: truncated inside the header")
    try:
        header = json.loads(data[len(CHECKPOINT_MAGIC):end])
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"{path}: header is not valid JSON (corrupted): {e}") from None
    if not isinstance(header, dict):
        raise CheckpointError(f"{path}: header is not a JSON object (corrupted)")
    version = header.get("format_version")
    if version not in versions:
        readable = " or ".join(str(v) for v in versions)
        hint = (" (a newer format: update ttsim_jax)" if isinstance(version, int) and version > max(versions)
                else " (written by an older ttsim_jax: retrain)")
        raise CheckpointError(f"{path}: key 'format_version' = {version!r}; this code reads "
                              f"{kind!r} files of version {readable}{hint}")
    if header.get("kind") != kind:
        raise CheckpointError(f"{path}: key 'kind' = {header.get('kind')!r}, expected {kind!r}")
    for key in ("payload_bytes", "payload_sha256", "arrays"):
        if key not in header:
            raise CheckpointError(f"{path}: header lacks key {key!r} (corrupted)")
    payload = data[end + 1:]
    if len(payload) != header["payload_bytes"]:
        raise CheckpointError(f"{path}: truncated or padded: key 'payload_bytes' says {header['payload_bytes']} "
                              f"bytes, the file holds {len(payload)}")
    if hashlib.sha256(payload).hexdigest() != header["payload_sha256"]:
        raise CheckpointError(f"{path}: corrupted: the payload does not match key 'payload_sha256'")
    try:
        arrays = serialization.msgpack_restore(payload)
    except Exception as e:  # msgpack raises several unrelated types
        raise CheckpointError(f"{path}: payload cannot be decoded (corrupted): {e}") from None
    flat = _flatten(arrays)
    listed = header["arrays"]
    if set(flat) != set(listed):
        raise CheckpointError(f"{path}: arrays {sorted(set(flat) ^ set(listed))} differ between header and payload")
    for k, v in flat.items():
        if [list(np.shape(v)), str(np.asarray(v).dtype)] != listed[k]:
            raise CheckpointError(f"{path}: key {k!r} is {np.shape(v)} {np.asarray(v).dtype} in the payload, "
                                  f"the header says {listed[k]}")
    _check_finite(path, flat)
    return header, arrays


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
    expected = _flatten(model_shapes(config))
    got = _flatten(arrays) if isinstance(arrays, dict) else {}
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
    write_container(path, "residual-model", header, _model_arrays(model))


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
    header, arrays = read_container(path, "residual-model", READABLE_MODEL_VERSIONS)
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
    header, _ = read_container(path, "residual-model", READABLE_MODEL_VERSIONS)
    return header.get("metadata", {})
