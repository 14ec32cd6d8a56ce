"""Reverse-mode Jacobians through the rally kernel against central finite differences (float64),
and the flags on gradients that hold only locally."""

import numpy as np
import pytest

from ttsim_jax.physics.events import RACKET, TABLE
from ttsim_jax.sensitivity.jacobians import STATE_GROUPS, finite_differences, group_directions, local_flags
from ttsim_jax.sensitivity.report import column_scales

# the module's fixture compiles the reverse pass through the kernel (minutes on 2 cores)
pytestmark = pytest.mark.slow


def test_shots_hit_the_racket_then_land(jac_all, cfg):
    shots, jac = jac_all
    assert jac.valid.all()
    assert (jac.sequence == [RACKET, TABLE]).all()
    # the moved shot lands on the side edge (centre beyond the playing surface's side), a few cm
    # further on than the drive it was moved from (it falls below the surface before touching the edge)
    assert jac.values[cfg["edge"], 1] > 0.7625 and abs(jac.values[cfg["edge"], 0] - jac.values[0, 0]) < 0.05


def test_jacobian_matches_central_differences_for_every_input_group(model, jac_all, cfg):
    shots, jac = jac_all
    scale = np.maximum(np.abs(jac.nominal).mean(0), 1e-3)
    dirs = group_directions(jac, np.random.default_rng(0), scale)
    names = list(dirs)
    assert set(STATE_GROUPS) <= set(names) and {"aero.drag", "aero.magnus", "table.restitution", "table.residual",
                                                 "racket.params"} <= set(names)
    fd, same, _ = finite_differences(model, shots, jac.nominal, np.stack([dirs[g] for g in names]), [1e-6],
                                     target="landing", dt=cfg["dt"], n_steps=cfg["n_steps"], batch=256)
    assert same.all()
    ad = np.einsum("bkc,dbc->dbk", jac.jac, np.stack([dirs[g] for g in names]))
    moving = 0
    for i, g in enumerate(names):
        for b in cfg["smooth"]:
            f, a = fd[0, i, b], ad[i, b]
            assert np.all(np.isfinite(a))
            if g in ("table.geometry", "constants") and np.max(np.abs(f)) < 1e-9:
                continue
            np.testing.assert_allclose(a, f, rtol=1e-2, atol=1e-2 * np.max(np.abs(f)) + 1e-9, err_msg=f"{g}, shot {b}")
            moving += np.max(np.abs(f)) > 1e-6
    # every state group and the model groups that shape the flight really move the landing point
    assert moving >= 2 * (len(STATE_GROUPS) - 1) + 6


def test_racket_orientation_column_is_a_rotation(jac_all, cfg):
    """d landing / d rotation vector about the face normal is a spin of the face about that normal,
    which changes neither the contact point's velocity nor the normal: its column is tiny against
    the tilt columns."""
    shots, jac = jac_all
    rot = jac.group("racket.rot")[cfg["smooth"]]  # (2, k, 3), world-frame rotation vector
    normal = shots.racket.rot[cfg["smooth"]][:, :, 0]
    about_normal = np.einsum("bkc,bc->bk", rot, normal)
    tilt = np.linalg.norm(rot, axis=-1)
    assert np.all(np.abs(about_normal) < 0.2 * tilt)


def test_edge_shot_is_flagged_smooth_shots_are_not(model, jac_all, cfg):
    shots, jac = jac_all
    scale = column_scales(jac)
    probe = {g: scale for g in ("racket.pos", "racket.rot", "racket.vel", "ball.spin")}
    flags = local_flags(model, shots, jac, probe, dt=cfg["dt"], n_steps=cfg["n_steps"], batch=256)
    assert flags["flag"].tolist() == [False, False, True]
    assert flags["flip"][cfg["edge"]] and not flags["flip"][cfg["smooth"]].any()
    # the flag is what finite differences at two step sizes say, checked here on the raw differences
    dirs = group_directions(jac, np.random.default_rng(0), scale)
    fd, same, _ = finite_differences(model, shots, jac.nominal, dirs["racket.rot"][None], [1.0, 1.0 / 8.0],
                                     target="landing", dt=cfg["dt"], n_steps=cfg["n_steps"], batch=256)
    gap = np.abs(fd[0, 0] - fd[1, 0]).max(-1) / np.abs(fd[1, 0]).max(-1)
    assert gap[cfg["edge"]] > 0.05 or not same[:, 0, cfg["edge"]].all()
    assert np.all(gap[cfg["smooth"]] < 0.05)
