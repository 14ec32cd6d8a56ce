"""The racket contact's residual neural network: its configuration, the network and its inference.

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
  (:func:`ttsim_jax.fit.network_stats.population_batch_stats`), which do not depend on the order
  of the batches.
* Sigma calibration: the predicted sigmas are multiplied by ``sigma_scale`` (6,), fitted on the
  validation split after training so that ~68.3 % of held-out errors fall inside one sigma
  (:func:`ttsim_jax.fit.network_stats.calibration_scale`). The Gaussian NLL alone leaves them
  over- or under-confident (early stopping, weight decay and dropout all bias them).

Training is :mod:`ttsim_jax.fit.network_training`, the configuration files are read by
:mod:`ttsim_jax.fit.network_config`, and a model's file is :mod:`ttsim_jax.physics.network_checkpoint`.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from ttsim_jax.errors import ConfigError

# The paper's authors' attenuation coefficients (beta = 1 for dist <= 0.150, 0 for dist >= 0.383).
PAPER_BETA = (7.282, 12.899, 0.052)

# Width of the (v~, w~) part of the input, on which the attenuation depends.
N_ATTENUATION_INPUTS = 6


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
