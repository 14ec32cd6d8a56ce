"""Padded, masked JAX batches."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ttsim_jax.data import EVENT_KINDS, event_batch, iter_segment_batches, racket_contact_batch, segment_batch
from ttsim_jax.data.batch import segment_lengths


def test_segment_batch_shapes_mask_and_values(small_dataset):
    ds = small_dataset
    b = segment_batch(ds)
    n = segment_lengths(ds)
    S, T = len(n), int(n.max())
    assert b.times.shape == (S, T) and b.positions.shape == (S, T, 3) and b.mask.shape == (S, T)
    assert b.spin.shape == (S, 3) and b.spin_conf.shape == (S,)
    np.testing.assert_array_equal(np.asarray(b.mask).sum(axis=1), n)
    # First segment: its samples, times relative to its start, padding repeats the last sample.
    rows = np.flatnonzero(ds.observations["segment_id"] == ds.segments["segment_id"][0])
    k = len(rows)
    np.testing.assert_allclose(np.asarray(b.positions[0, :k]), ds.positions[rows], atol=1e-6)
    np.testing.assert_allclose(np.asarray(b.times[0, :k]) + float(b.t0[0]), ds.observations["t"][rows], atol=1e-5)
    assert float(b.times[0, 0]) == 0.0
    if k < T:
        np.testing.assert_array_equal(np.asarray(b.positions[0, k:]), np.repeat(np.asarray(b.positions[0, k - 1 : k]), T - k, 0))
    assert float(b.spin_conf[0]) > 0.5 and float(b.spin[0, 1]) == 150.0


def test_segment_batch_is_a_jittable_pytree(small_dataset):
    b = segment_batch(small_dataset)

    @jax.jit
    def masked_mean_height(batch):
        return jnp.sum(batch.positions[..., 2] * batch.mask) / jnp.sum(batch.mask)

    z = small_dataset.observations["z"][small_dataset.observations["segment_id"] >= 0]
    assert abs(float(masked_mean_height(b)) - z.mean()) < 1e-4


def test_iter_batches_have_one_shape_and_cover_everything(small_dataset):
    n = len(small_dataset.segments["segment_id"])
    batches = list(iter_segment_batches(small_dataset, 3, shuffle=True, seed=1))
    assert len(batches) == -(-n // 3)
    assert len({b.times.shape for b in batches}) == 1
    ids = np.concatenate([np.asarray(b.segment_id) for b in batches])
    assert sorted(ids[ids >= 0].tolist()) == sorted(small_dataset.segments["segment_id"].tolist())
    last = batches[-1]
    pad = np.asarray(last.segment_id) == -1
    assert pad.sum() == 3 * len(batches) - n and not np.asarray(last.mask)[pad].any()


def test_event_and_racket_batches(small_dataset):
    ds = small_dataset
    e = event_batch(ds, pad_to=8)
    n = len(ds.events["event_id"])
    assert int(e.mask.sum()) == n and e.kind.shape == (8,)
    assert [EVENT_KINDS[k] for k in np.asarray(e.kind[:n])] == list(ds.events["kind"])
    tables = event_batch(ds, kinds=("table",))
    assert int(tables.mask.sum()) == int((ds.events["kind"] == "table").sum())

    r = racket_contact_batch(ds, pad_to=2)
    assert r.racket_quat.shape == (2, 4) and bool(r.mask[0]) and not bool(r.mask[1])
    np.testing.assert_allclose(np.linalg.norm(np.asarray(r.racket_quat), axis=1), 1.0, atol=1e-6)
    # The racket event closes session 0's last segment and opens none.
    seg_row = int(r.in_segment[0])
    assert ds.segments["end_event_id"][seg_row] == ds.rackets["event_id"][0]
    assert int(r.out_segment[0]) == -1
    np.testing.assert_allclose(np.asarray(r.contact_point[0]), [0.01, -0.02], atol=1e-7)
