"""Training the racket residual network (:mod:`ttsim_jax.physics.network`) on contact data.

Inputs are plain arrays, one row per contact, all in the racket frame:

* ``x`` (N, n_inputs): pre-contact inputs (v~, w~[, d]).
* ``y_base`` (N, 6): the base model's post-contact prediction (v+, w+).
* ``y_obs`` (N, 6): the observed post-contact state.

The network learns the residual y_obs - y_base by minimising the paper's Gaussian negative
log-likelihood, L = mean_i sum_j w_j [log sigma_ij + (r_ij - rhat_ij)^2 / (2 sigma_ij^2)], with
equal component weights by default (``loss_weights``; see
:class:`~ttsim_jax.fit.network_config.TrainConfig` for why not the authors' x100 on velocity). The
data are split 80/10/10 by contact; input scaling, output standardisation and the k-means centres
come from the training split only; early stopping watches the validation loss; the test split
gives the report. Training state is checkpointed atomically and can be resumed.

After training (and for every epoch's validation loss) the batch-norm statistics are the exact
population statistics of the training split
(:func:`ttsim_jax.fit.network_stats.population_batch_stats`), not the running averages; then one
factor per output component (or per velocity / spin group) is fitted on the validation split so
that about 68.3 % of its errors lie inside one predicted sigma (``ResidualModel.sigma_scale``,
:func:`ttsim_jax.fit.network_evaluation.calibrate_sigma`); the test split reports the coverage
reached.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import time
from functools import lru_cache
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization
from tqdm.auto import tqdm

from ttsim_jax.files.atomic import remove_leftovers
from ttsim_jax.files.checkpoint import CheckpointError, read_container, write_container
from ttsim_jax.fit.network_config import TrainConfig
from ttsim_jax.fit.network_evaluation import calibrate_sigma, evaluate_residual
from ttsim_jax.fit.network_stats import calibrate_beta, kmeans, population_batch_stats
from ttsim_jax.physics.network import (N_ATTENUATION_INPUTS, ResidualConfig, ResidualModel, ResidualNet,
                                       init_variables, nearest_distance)

TRAIN_STATE_KIND = "residual-train-state"


# ----------------------------------------------------------------------------------------------
# Training


def split_by_contact(n: int, fractions=(0.8, 0.1, 0.1), seed: int = 0, groups=None):
    """Train / validation / test indices, whole contacts to one split.

    Arguments:
        n: number of rows.
        fractions: (train, val, test).
        seed: seed of the shuffle.
        groups: optional (n,) contact id of each row (rows of one contact stay together);
            default: every row is its own contact.

    Returns:
        (train_idx, val_idx, test_idx), sorted int arrays.
    """
    groups = np.arange(n) if groups is None else np.asarray(groups)
    ids = np.unique(groups)
    if len(ids) < 3:
        raise ValueError(f"split_by_contact: need at least 3 contacts, got {len(ids)}")
    ids = np.random.default_rng(seed).permutation(ids)
    n_val = max(1, int(round(fractions[1] * len(ids))))
    n_test = max(1, int(round(fractions[2] * len(ids))))
    n_train = len(ids) - n_val - n_test
    if n_train < 1:
        raise ValueError(f"split_by_contact: {len(ids)} contacts leave no training contact")
    parts = (ids[:n_train], ids[n_train:n_train + n_val], ids[n_train + n_val:])
    return tuple(np.sort(np.nonzero(np.isin(groups, p))[0]) for p in parts)


def gaussian_nll(mu_n, log_sigma_n, y_n, weights, log_scale):
    """The paper's weighted Gaussian NLL, mean over rows, in physical units.

    Standardised targets y_n = (y - mean) / scale give sigma = scale sigma_n, so the physical NLL
    equals the standardised one plus sum_j w_j log scale_j (the constant is added so that the
    value is the paper's L).

    Arguments:
        mu_n, log_sigma_n, y_n: (N, 6) standardised predictions, log sigmas, targets.
        weights: (6,) component weights.
        log_scale: (6,) log of the standardisation scales.

    Returns:
        scalar loss.
    """
    per = log_sigma_n + 0.5 * ((y_n - mu_n) * jnp.exp(-log_sigma_n)) ** 2
    return jnp.mean(jnp.sum(weights * per, axis=1)) + jnp.sum(weights * log_scale)


def _optimizer(tcfg: TrainConfig, steps_per_epoch: int):
    total = tcfg.max_epochs * steps_per_epoch
    warmup = min(max(1, tcfg.warmup_epochs * steps_per_epoch), max(1, total - 1))
    schedule = optax.warmup_cosine_decay_schedule(
        init_value=0.0, peak_value=tcfg.learning_rate, warmup_steps=warmup,
        decay_steps=max(total, warmup + 1), end_value=tcfg.learning_rate * tcfg.end_lr_factor)
    return optax.adamw(schedule, weight_decay=tcfg.weight_decay)


@lru_cache(maxsize=16)
def _train_functions(config: ResidualConfig, tcfg: TrainConfig, steps_per_epoch: int):
    """Jitted (epoch, loss) functions for one architecture and schedule; cached so that resumed
    or repeated runs reuse the compilation."""
    net = ResidualNet(config)
    opt = _optimizer(tcfg, steps_per_epoch)
    weights = jnp.asarray(tcfg.loss_weights, jnp.float32)
    bs = tcfg.batch_size

    def split_out(out):
        dv, dw, lsv, lsw = out
        return jnp.concatenate([dv, dw], 1), jnp.concatenate([lsv, lsw], 1)

    @jax.jit
    def epoch(params, batch_stats, opt_state, xs, ys, log_scale, key):
        k_perm, k_drop = jax.random.split(key)
        order = jax.random.permutation(k_perm, xs.shape[0])[: steps_per_epoch * bs].reshape(steps_per_epoch, bs)

        def step(carry, inp):
            params, batch_stats, opt_state = carry
            idx, i = inp

            def loss_fn(p):
                out, new = net.apply({"params": p, "batch_stats": batch_stats}, xs[idx], train=True,
                                     rngs={"dropout": jax.random.fold_in(k_drop, i)}, mutable=["batch_stats"])
                mu, ls = split_out(out)
                return gaussian_nll(mu, ls, ys[idx], weights, log_scale), new["batch_stats"]

            (loss, batch_stats), grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
            updates, opt_state = opt.update(grads, opt_state, params)
            return (optax.apply_updates(params, updates), batch_stats, opt_state), loss

        (params, batch_stats, opt_state), losses = jax.lax.scan(
            step, (params, batch_stats, opt_state), (order, jnp.arange(steps_per_epoch)))
        return params, batch_stats, opt_state, jnp.mean(losses)

    @jax.jit
    def eval_loss(variables, xs, ys, log_scale):
        mu, ls = split_out(net.apply(variables, xs, train=False))
        return gaussian_nll(mu, ls, ys, weights, log_scale)

    return epoch, eval_loss, opt


def _fingerprint(arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.shape, a.dtype.str)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _prepare(config: ResidualConfig, tcfg: TrainConfig, x, target, train_idx, val_idx):
    """Scaling, standardisation and k-means centres from the training split; calibrated beta."""
    xt = x[train_idx]
    x_min, x_max = xt.min(axis=0), xt.max(axis=0)
    y_mean = target[train_idx].mean(axis=0)
    y_scale = np.maximum(target[train_idx].std(axis=0), 1e-6)
    span = np.maximum(x_max - x_min, 1e-12)
    xs_train = ((xt - x_min) / span).astype(np.float32)
    xs_val = ((x[val_idx] - x_min) / span).astype(np.float32)
    if config.n_clusters > len(train_idx):
        raise ValueError(f"n_clusters = {config.n_clusters} exceeds the {len(train_idx)} training contacts; "
                         "lower [model] n_clusters")
    centres = kmeans(jnp.asarray(xs_train[:, :N_ATTENUATION_INPUTS]), config.n_clusters,
                     jax.random.key(tcfg.seed + 17), iters=tcfg.kmeans_iters)
    dist_val = np.asarray(nearest_distance(jnp.asarray(xs_val[:, :N_ATTENUATION_INPUTS]), centres))
    coef = (config.beta_a, config.beta_b, config.beta_c)
    new_coef, info = calibrate_beta(dist_val, *coef, quantile=tcfg.attenuation_quantile)
    if tcfg.attenuation == "paper":
        new_coef = coef
        info = dict(info, rescaled=False, note="attenuation='paper': coefficients kept, info for reference only")
    f32 = lambda a: jnp.asarray(np.asarray(a, np.float32))  # noqa: E731
    pre = dict(x_min=f32(x_min), x_max=f32(x_max), y_mean=f32(y_mean), y_scale=f32(y_scale),
               centres=f32(centres), beta_coef=f32(new_coef))
    return pre, info


def _state_tree(params, batch_stats, opt_state, best_variables, pre):
    return dict(params=params, batch_stats=batch_stats, opt_state=opt_state, best_variables=best_variables, pre=pre)


def _check_inputs(config, x, y_base, y_obs, groups):
    n = x.shape[0] if x.ndim == 2 else -1
    if x.ndim != 2 or x.shape[1] != config.n_inputs:
        raise ValueError(f"train_residual: x has shape {x.shape}; config n_inputs = {config.n_inputs} "
                         f"needs (N, {config.n_inputs})")
    for name, y in (("y_base", y_base), ("y_obs", y_obs)):
        if y.shape != (n, 6):
            raise ValueError(f"train_residual: {name} has shape {y.shape}, expected ({n}, 6)")
    for name, a in (("x", x), ("y_base", y_base), ("y_obs", y_obs)):
        bad = ~np.isfinite(a)
        if bad.any():
            row = int(np.nonzero(bad.any(axis=1))[0][0])
            raise ValueError(f"train_residual: {name} has non-finite values (first at row {row}: {a[row].tolist()})")
    if groups is not None and np.shape(groups) != (n,):
        raise ValueError(f"train_residual: groups has shape {np.shape(groups)}, expected ({n},)")


def train_residual(x, y_base, y_obs, config: ResidualConfig, tcfg: TrainConfig = TrainConfig(), groups=None,
                   checkpoint=None, resume: bool = False, progress: bool = True,
                   callback: Callable | None = None) -> tuple[ResidualModel, dict]:
    """Trains the residual network on contacts; returns the best (early-stopped) model.

    Arguments:
        x: (N, n_inputs) racket-frame pre-contact inputs.
        y_base: (N, 6) base-model racket-frame post-contact (v+, w+).
        y_obs: (N, 6) observed racket-frame post-contact (v+, w+).
        config: the network architecture.
        tcfg: training hyper-parameters.
        groups: optional (N,) contact ids for the split (default: one row per contact).
        checkpoint: optional path of the training-state file, written atomically every
            ``tcfg.checkpoint_every`` epochs, on interruption and at the end; temporaries left
            beside it by a killed run are removed. A state holding non-finite arrays is refused
            (at save and at load).
        resume: continue from ``checkpoint`` (it must come from the same data and settings; a
            finished run returns its result at once). Without ``resume`` an existing checkpoint
            is never overwritten: an error asks for resume=True or another path.
        progress: show a tqdm bar with per-epoch train and validation loss.
        callback: optional fn(epoch, logs) called after each epoch (raising stops training;
            the state of the last completed epoch is saved first).

    Returns:
        (model, report): the :class:`ResidualModel` with the lowest validation loss (with
        population batch-norm statistics and calibrated sigmas, as ``tcfg`` says), and the
        held-out (test split) report of :func:`evaluate_residual` plus the training history,
        split sizes, attenuation and sigma calibration.
    """
    x = np.asarray(x, np.float32)
    y_base = np.asarray(y_base, np.float32)
    y_obs = np.asarray(y_obs, np.float32)
    _check_inputs(config, x, y_base, y_obs, groups)
    target = y_obs - y_base
    train_idx, val_idx, test_idx = split_by_contact(len(x), tcfg.split, tcfg.seed, groups)
    bs = min(tcfg.batch_size, len(train_idx))
    steps = len(train_idx) // bs
    run_tcfg = dataclasses.replace(tcfg, batch_size=bs)
    epoch_fn, eval_loss, opt = _train_functions(config, run_tcfg, steps)

    hashed = [x, y_base, y_obs] + ([np.asarray(groups)] if groups is not None else [])
    fingerprint = dict(data_sha256=_fingerprint(hashed),
                       config=config.to_dict(), train_config=tcfg.to_dict())
    pre, beta_info = _prepare(config, tcfg, x, target, train_idx, val_idx)
    variables = init_variables(config, jax.random.key(tcfg.seed))
    params, batch_stats = variables["params"], variables["batch_stats"]
    opt_state = opt.init(params)
    best_variables = variables
    meta = dict(epoch=0, best_epoch=0, best_val=math.inf, bad_epochs=0, finished=False, history=[])

    if checkpoint is not None:
        remove_leftovers(checkpoint)  # temporaries of a killed earlier run
    if checkpoint is not None and os.path.exists(checkpoint):
        if not resume:
            raise FileExistsError(f"{checkpoint}: a training checkpoint already exists; pass resume=True to "
                                  "continue it, or choose another path (it is never overwritten)")
        header, arrays = read_container(checkpoint, TRAIN_STATE_KIND)
        for key, value in fingerprint.items():
            if header.get(key) != value:
                raise CheckpointError(f"{checkpoint}: key {key!r} differs from this run's (different data or "
                                      f"settings); resume with the original ones or choose another path")
        template = _state_tree(params, batch_stats, opt_state, best_variables, pre)
        try:
            restored = serialization.from_state_dict(template, arrays)
        except (ValueError, KeyError, TypeError) as e:
            raise CheckpointError(f"{checkpoint}: training state does not fit this configuration: {e}") from None
        for (where, a), b in zip(jax.tree_util.tree_flatten_with_path(template)[0],
                                 jax.tree_util.tree_leaves(restored)):
            if np.shape(a) != np.shape(b):
                raise CheckpointError(f"{checkpoint}: key {jax.tree_util.keystr(where)!r} has shape "
                                      f"{np.shape(b)}, expected {np.shape(a)}")
        to_j = lambda t: jax.tree_util.tree_map(jnp.asarray, t)  # noqa: E731
        params, batch_stats = to_j(restored["params"]), to_j(restored["batch_stats"])
        opt_state = to_j(restored["opt_state"])
        best_variables, pre = to_j(restored["best_variables"]), to_j(restored["pre"])
        beta_info = header.get("beta_info", beta_info)
        lacking = sorted(set(meta) - set(header))
        if lacking:
            raise CheckpointError(f"{checkpoint}: header lacks key(s) {lacking}")
        meta = {k: header[k] for k in meta}
        if meta["best_val"] is None:
            meta["best_val"] = math.inf

    def save_state():
        if checkpoint is None:
            return
        head = dict(fingerprint, beta_info=beta_info, **{k: (None if v == math.inf else v) for k, v in meta.items()})
        write_container(checkpoint, TRAIN_STATE_KIND, head, serialization.to_state_dict(
            _state_tree(params, batch_stats, opt_state, best_variables, pre)))

    x_min, span = np.asarray(pre["x_min"]), np.maximum(np.asarray(pre["x_max"] - pre["x_min"]), 1e-12)
    xs_tr, xs_va = jnp.asarray((x[train_idx] - x_min) / span), jnp.asarray((x[val_idx] - x_min) / span)
    std = lambda y: jnp.asarray((y - np.asarray(pre["y_mean"])) / np.asarray(pre["y_scale"]))  # noqa: E731
    ys_tr, ys_va = std(target[train_idx]), std(target[val_idx])
    log_scale = jnp.log(pre["y_scale"])
    key = jax.random.key(tcfg.seed + 1)

    saved_epoch = meta["epoch"]
    bar = tqdm(total=tcfg.max_epochs, initial=meta["epoch"], disable=not progress, desc="residual", unit="epoch")
    t0 = time.perf_counter()
    try:
        while not meta["finished"] and meta["epoch"] < tcfg.max_epochs:
            e = meta["epoch"]
            new = epoch_fn(params, batch_stats, opt_state, xs_tr, ys_tr, log_scale, jax.random.fold_in(key, e))
            train_loss = float(new[3])
            if not math.isfinite(train_loss):  # checked before adopting, so no checkpoint holds NaNs
                raise FloatingPointError(f"train_residual: training loss became {train_loss} at epoch {e + 1}; "
                                         "lower the learning rate")
            params, batch_stats, opt_state = new[:3]
            variables = {"params": params, "batch_stats": batch_stats}
            if tcfg.population_stats:
                variables = population_batch_stats(variables, config, xs_tr)
            val_loss = float(eval_loss(variables, xs_va, ys_va, log_scale))
            meta["epoch"] = e + 1
            meta["history"].append([train_loss, val_loss])
            if val_loss < meta["best_val"] - tcfg.min_delta:
                meta.update(best_val=val_loss, best_epoch=e + 1, bad_epochs=0)
                best_variables = variables
            else:
                meta["bad_epochs"] += 1
            if meta["bad_epochs"] >= tcfg.patience or meta["epoch"] >= tcfg.max_epochs:
                meta["finished"] = True
            bar.update(1)
            bar.set_postfix(train=f"{train_loss:.4g}", val=f"{val_loss:.4g}", best=f"{meta['best_val']:.4g}")
            if meta["finished"] or meta["epoch"] % tcfg.checkpoint_every == 0:
                save_state()
                saved_epoch = meta["epoch"]
            if callback is not None:
                callback(meta["epoch"], dict(train_loss=train_loss, val_loss=val_loss, best_val=meta["best_val"]))
    except BaseException:
        if meta["epoch"] != saved_epoch:  # keep the last completed epoch's work
            save_state()
        raise
    finally:
        bar.close()
    if meta["epoch"] != saved_epoch or (checkpoint is not None and not os.path.exists(checkpoint)):
        save_state()

    if tcfg.population_stats:  # idempotent for a fresh run; makes the final statistics explicit
        best_variables = population_batch_stats(best_variables, config, xs_tr)
    model = ResidualModel(variables=best_variables, config=config, sigma_scale=jnp.ones((6,), jnp.float32), **pre)
    model, calib = calibrate_sigma(model, x[val_idx], y_base[val_idx], y_obs[val_idx], tcfg.calibration,
                                   tcfg.calibration_target)
    report = evaluate_residual(model, x[test_idx], y_base[test_idx], y_obs[test_idx])
    report.update(
        n_train=len(train_idx), n_val=len(val_idx), n_test=len(test_idx), batch_size=bs,
        epochs=meta["epoch"], best_epoch=meta["best_epoch"], best_val_loss=meta["best_val"],
        early_stopped=meta["epoch"] < tcfg.max_epochs, history=meta["history"],
        attenuation=dict(beta_info, coefficients=[float(c) for c in np.asarray(pre["beta_coef"])]),
        sigma_calibration=calib, batch_stats="population" if tcfg.population_stats else "running",
        train_seconds_this_call=time.perf_counter() - t0,
    )
    return model, report
