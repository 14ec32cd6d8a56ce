"""Residual checkpoints: bit-exact round trip, clear errors for bad files, resumable training."""

import json
import os
import subprocess

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax.files import checkpoint as container
from ttsim_jax.files.checkpoint import CHECKPOINT_MAGIC, CheckpointError, read_container, write_container
from ttsim_jax.fit.network_config import TrainConfig
from ttsim_jax.fit.network_training import train_residual
from ttsim_jax.reality.synthetic_contacts import make_synthetic_contacts
from ttsim_jax.physics.network import ResidualConfig, init_model, residual_outputs
from ttsim_jax.physics.network_checkpoint import checkpoint_metadata, load_residual, model_arrays, save_residual

CFG = ResidualConfig(trunk=(16, 16), head_width=8, n_clusters=12, dropout=0.1)


def _model(seed=0, config=CFG):
    m = init_model(config, jax.random.key(seed))
    rng = np.random.default_rng(seed + 1)  # host-side noise: op-by-op device calls are slow
    v = jax.tree_util.tree_map(lambda a: jnp.asarray(np.asarray(a) + rng.normal(size=a.shape).astype(a.dtype)),
                               m.variables)
    return m.replace(variables=v, x_min=m.x_min - 3.0,
                     centres=jnp.asarray(rng.uniform(size=m.centres.shape).astype(np.float32)))


def _leaves_equal(a, b):
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    def same(x, y):
        x, y = np.asarray(x), np.asarray(y)
        return x.dtype == y.dtype and np.array_equal(x, y)

    return len(la) == len(lb) and all(same(x, y) for x, y in zip(la, lb))


def test_round_trip_bit_exact(tmp_path):
    m = _model()
    path = tmp_path / "net.ttres"
    save_residual(path, m, metadata={"note": "test"})
    back = load_residual(path, expected_config=CFG)
    assert back.config == m.config
    assert jax.tree_util.tree_structure(back) == jax.tree_util.tree_structure(m)
    assert _leaves_equal(back, m)
    assert checkpoint_metadata(path) == {"note": "test"}
    # the atomic writer leaves no temporary file behind
    assert sorted(os.listdir(tmp_path)) == ["net.ttres"]


def test_truncated_file_is_named(tmp_path):
    path = tmp_path / "net.ttres"
    save_residual(path, _model())
    data = path.read_bytes()
    for cut in (len(data) - 10, len(data) // 2, 30, 5):
        bad = tmp_path / f"cut{cut}.ttres"
        bad.write_bytes(data[:cut])
        with pytest.raises(CheckpointError, match=str(bad).replace("\\", "\\\\")):
            load_residual(bad)
    with pytest.raises(CheckpointError, match="payload_bytes"):
        load_residual(tmp_path / f"cut{len(data) - 10}.ttres")


def test_corrupted_byte_and_version(tmp_path):
    path = tmp_path / "net.ttres"
    save_residual(path, _model())
    data = bytearray(path.read_bytes())
    data[-20] ^= 0xFF
    bad = tmp_path / "flip.ttres"
    bad.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="payload_sha256"):
        load_residual(bad)

    raw = path.read_bytes()
    end = raw.index(b"\n", len(CHECKPOINT_MAGIC))
    header = json.loads(raw[len(CHECKPOINT_MAGIC):end])
    header["format_version"] = 99
    newer = tmp_path / "v99.ttres"
    newer.write_bytes(CHECKPOINT_MAGIC + json.dumps(header).encode() + raw[end:])
    with pytest.raises(CheckpointError, match="header_sha256"):  # an edited header: its own sum disagrees
        load_residual(newer)
    del header["header_sha256"]  # as a writer that does not sum its header
    newer.write_bytes(CHECKPOINT_MAGIC + json.dumps(header).encode() + raw[end:])
    with pytest.raises(CheckpointError, match="format_version"):
        load_residual(newer)
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        load_residual(tmp_path / "missing.ttres")


def test_mismatched_shapes_name_the_key(tmp_path):
    m8 = _model()
    # a self-consistent file (valid checksum) whose arrays do not fit its configuration
    six = ResidualConfig(n_inputs=6, trunk=(16, 16), head_width=8, n_clusters=12, dropout=0.1)
    path = tmp_path / "mixed.ttres"
    write_container(path, "residual-model", dict(config=six.to_dict(), metadata={}), model_arrays(m8))
    with pytest.raises(CheckpointError, match=r"mixed\.ttres.*'variables/params/trunk_0/kernel' has shape \(8, 16\)"):
        load_residual(path)

    good = tmp_path / "good.ttres"
    save_residual(good, m8)
    other = ResidualConfig(trunk=(32, 16), head_width=8, n_clusters=12, dropout=0.1)
    with pytest.raises(CheckpointError, match="does not match the expected configuration"):
        load_residual(good, expected_config=other)

    arrays = model_arrays(m8)
    del arrays["centres"]
    partial = tmp_path / "partial.ttres"
    write_container(partial, "residual-model", dict(config=CFG.to_dict(), metadata={}), arrays)
    with pytest.raises(CheckpointError, match="missing array 'centres'"):
        load_residual(partial)


def _data(n=600, seed=3):
    return make_synthetic_contacts(n, seed)


def test_training_resume_matches_uninterrupted(tmp_path):
    d = _data()
    tc = TrainConfig(batch_size=32, max_epochs=5, patience=100, kmeans_iters=5, seed=1)
    ref_model, ref = train_residual(d["x"], d["y_base"], d["y_obs"], CFG, tc, checkpoint=tmp_path / "a.state",
                                    progress=False)

    class Stop(Exception):
        pass

    def stop_at_2(epoch, logs):
        if epoch == 2:
            raise Stop()

    ck = tmp_path / "b.state"
    with pytest.raises(Stop):
        train_residual(d["x"], d["y_base"], d["y_obs"], CFG, tc, checkpoint=ck, progress=False, callback=stop_at_2)
    with pytest.raises(FileExistsError, match="resume=True"):
        train_residual(d["x"], d["y_base"], d["y_obs"], CFG, tc, checkpoint=ck, progress=False)
    # a run killed while writing its state leaves a temporary beside it; resuming removes it
    dead = subprocess.Popen(["true"])
    dead.wait()
    leftover = tmp_path / f".b.state.{dead.pid}.1234abcd.tmp"
    leftover.write_bytes(ck.read_bytes()[:100])
    model, rep = train_residual(d["x"], d["y_base"], d["y_obs"], CFG, tc, checkpoint=ck, resume=True,
                                progress=False)
    assert rep["history"] == ref["history"] and rep["epochs"] == 5
    assert _leaves_equal(model, ref_model)
    assert not leftover.exists()
    # a finished run resumes to its result without training
    again, rep2 = train_residual(d["x"], d["y_base"], d["y_obs"], CFG, tc, checkpoint=ck, resume=True,
                                 progress=False)
    assert _leaves_equal(again, ref_model) and rep2["history"] == ref["history"]

    other = _data(seed=4)
    with pytest.raises(CheckpointError, match="data_sha256"):
        train_residual(other["x"], other["y_base"], other["y_obs"], CFG, tc, checkpoint=ck, resume=True,
                       progress=False)


def test_version_1_model_loads_uncalibrated_with_a_warning(tmp_path):
    m = _model().replace(sigma_scale=jnp.full((6,), 2.0, jnp.float32))
    arrays = model_arrays(m)
    del arrays["sigma_scale"]
    path = tmp_path / "v1.ttres"
    write_container(path, "residual-model", dict(config=CFG.to_dict(), metadata={}), arrays)
    raw = path.read_bytes()
    end = raw.index(b"\n", len(CHECKPOINT_MAGIC))
    header = json.loads(raw[len(CHECKPOINT_MAGIC):end])
    header["format_version"] = 1
    del header["header_sha256"]  # version-1 files were written before headers carried their sum
    path.write_bytes(CHECKPOINT_MAGIC + json.dumps(header).encode() + raw[end:])
    with pytest.warns(UserWarning, match="version 1 has no sigma calibration"):
        back = load_residual(path)
    assert np.all(np.asarray(back.sigma_scale) == 1.0)
    assert _leaves_equal(back.variables, m.variables)
    # a version-2 file must hold sigma_scale
    v2 = tmp_path / "v2.ttres"
    write_container(v2, "residual-model", dict(config=CFG.to_dict(), metadata={}), arrays)
    with pytest.raises(CheckpointError, match="missing array 'sigma_scale'"):
        load_residual(v2)
    # training states are read in the current version only
    state = tmp_path / "old.state"
    header["kind"] = "residual-train-state"
    state.write_bytes(CHECKPOINT_MAGIC + json.dumps(header).encode() + raw[end:])
    with pytest.raises(CheckpointError, match="format_version' = 1.*version 2"):
        read_container(state, "residual-train-state")


def test_sigma_scale_round_trips_and_scales_sigmas(tmp_path):
    m = _model().replace(sigma_scale=jnp.asarray([1.0, 2.0, 3.0, 0.5, 1.0, 4.0], jnp.float32))
    path = tmp_path / "s.ttres"
    save_residual(path, m)
    back = load_residual(path)
    assert _leaves_equal(back, m)
    x = jnp.zeros((3, 8)) + 0.5
    outputs = jax.jit(residual_outputs)
    a = outputs(m, x)
    b = outputs(m.replace(sigma_scale=jnp.ones(6, jnp.float32)), x)
    np.testing.assert_allclose(np.asarray(a["sigma_v"]), np.asarray(b["sigma_v"]) * [1.0, 2.0, 3.0], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(a["sigma_w"]), np.asarray(b["sigma_w"]) * [0.5, 1.0, 4.0], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(a["dv"]), np.asarray(b["dv"]))


def test_non_finite_arrays_are_refused_at_save_and_at_load(tmp_path, monkeypatch):
    m = _model()
    path = tmp_path / "net.ttres"
    save_residual(path, m)
    good = path.read_bytes()
    (where, _), *_ = jax.tree_util.tree_flatten_with_path(m.variables)[0]
    bad = m.replace(variables=jax.tree_util.tree_map_with_path(
        lambda p, a: a.at[(0,) * a.ndim].set(jnp.nan) if p == where else a, m.variables))
    key = "/".join(["variables"] + [str(k.key) for k in where])
    with pytest.raises(CheckpointError) as e:
        save_residual(path, bad)
    assert str(path) in str(e.value) and repr(key) in str(e.value) and "non-finite" in str(e.value)
    assert path.read_bytes() == good and sorted(os.listdir(tmp_path)) == ["net.ttres"]  # the old file stays
    # a file holding NaNs (written by other means) is refused at load, naming the key
    monkeypatch.setattr(container, "_check_finite", lambda *a: None)
    save_residual(tmp_path / "nan.ttres", bad)
    monkeypatch.undo()
    with pytest.raises(CheckpointError) as e:
        load_residual(tmp_path / "nan.ttres")
    assert str(tmp_path / "nan.ttres") in str(e.value) and repr(key) in str(e.value)
