"""The gusts of the ``air_flow`` candidate (:mod:`ttsim_jax.diagnose.gusts`): the periodogram of
per-segment wind offsets, the offsets themselves, and the two-descent fit of the candidate on
flights flown through gusts in session time.

The flights are made here with the diagnosis's own flight stage (one session, 96 segments of
0.25 s spread over 60 s, 1 mm of position noise), so the test needs no generator run.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ttsim_jax import effects as fx
from ttsim_jax import load_model
from ttsim_jax.diagnose import candidates as C
from ttsim_jax.diagnose import stages as S
from ttsim_jax.diagnose.gusts import MIN_CHI2, SCALES, mean_times, periodogram_gusts, segment_winds
from ttsim_jax.diagnose.phases import Flights, Phases, pad_rows

WIND = np.array([0.25, -0.1, 0.0])
GUST_AMP = np.array([[0.0, 0.3, 0.0], [0.2, 0.0, 0.0], [0.0, 0.0, 0.0]])
GUST_FREQ = np.array([0.23, 0.61, 0.5])
GUST_PHASE = np.array([0.7, -1.9, 0.0])


def _sinusoids(t, amp, freq, phase):
    return sum(a[None] * np.sin(2 * np.pi * f * t + p)[:, None] for a, f, p in zip(amp, freq, phase))


def test_periodogram_finds_the_gusts_and_nothing_in_noise():
    rng = np.random.default_rng(1)
    t = np.sort(rng.uniform(0.0, 100.0, 140))
    amp, freq, phase = np.array([[0.1, -0.05, 0.02], [0.0, 0.08, 0.0]]), np.array([0.137, 0.61]), np.array([0.4, -2.0])
    noise = 0.02
    info = np.broadcast_to(np.eye(3) / noise**2, (len(t), 3, 3))
    w = 0.3 + _sinusoids(t, amp, freq, phase) + rng.normal(0.0, noise, (len(t), 3))
    a, f, p, chi2 = periodogram_gusts(t, w, info)
    assert np.all(chi2[:2] > MIN_CHI2) and not a[2].any(), chi2
    for k in range(2):
        assert abs(f[k] - freq[k]) < 0.003, f
        # one sign of (amplitude, phase) or the other: the same sinusoid
        fit = _sinusoids(t, a[k:k + 1], f[k:k + 1], p[k:k + 1])
        true = _sinusoids(t, amp[k:k + 1], freq[k:k + 1], phase[k:k + 1])
        assert np.sqrt(np.mean((fit - true) ** 2)) < 0.2 * np.sqrt(np.mean(true**2)), k
    a0, _, _, chi0 = periodogram_gusts(t, rng.normal(0.0, noise, (len(t), 3)), info)
    assert not a0.any() and chi0[0] < MIN_CHI2, chi0


def test_scatter_beyond_the_stated_noise_is_not_taken_for_gusts():
    """Offsets scattered 5 times more than their information says (other unmodelled effects, segment
    by segment): no component, though their raw chi-square at the best frequency is far above the
    threshold."""
    rng = np.random.default_rng(2)
    t = np.sort(rng.uniform(0.0, 100.0, 85))
    info = np.broadcast_to(np.eye(3) / 0.01**2, (len(t), 3, 3))
    w = 0.3 + rng.normal(0.0, 0.05, (len(t), 3))
    a, _, _, chi2 = periodogram_gusts(t, w, info)
    assert not a.any() and chi2[0] < MIN_CHI2, chi2
    # a real gust of the same size as that scatter is still found
    w = w + _sinusoids(t, np.array([[0.1, 0.1, 0.0]]), np.array([0.3]), np.array([0.5]))
    a, f, _, _ = periodogram_gusts(t, w, info)
    assert np.linalg.norm(a[0]) > 0.05 and abs(f[0] - 0.3) < 0.005, (a, f)


# ---------------------------------------------------------------------------------------------- flights
@pytest.fixture(scope="module")
def model():
    return load_model("conti2026", dtype=jnp.float32)


def _air(cls, **values):
    vals = {k: jnp.asarray(np.broadcast_to(p.neutral, p.shape), jnp.float32) for k, p in cls.PARAMS.items()}
    vals.update({k: jnp.asarray(v, jnp.float32) for k, v in values.items()})
    return cls(**vals)


def _flights(model, air, n=96, samples=26, seed=0, noise=0.001, cut=()):
    """Flights of one session through ``air`` (an AirFlow), as the diagnosis's Phases; the segments
    ``cut`` are cut wrongly: their second half is a mirrored flight, as if a bounce fell inside."""
    rng = np.random.default_rng(seed)
    rows = pad_rows(n)
    t0 = np.sort(rng.uniform(0.0, 60.0, n))
    tau = np.broadcast_to(np.arange(samples) * 0.01, (n, samples))
    p0 = np.stack([rng.uniform(-1.4, -1.0, n), rng.uniform(-0.3, 0.3, n), rng.uniform(0.2, 0.35, n)], -1)
    v0 = np.stack([rng.uniform(6.0, 11.0, n), rng.uniform(-1.0, 1.0, n), rng.uniform(0.5, 2.0, n)], -1)
    w0 = np.stack([rng.uniform(-30, 30, n), rng.uniform(-150, 150, n), rng.uniform(-30, 30, n)], -1)
    fly = jax.jit(jax.vmap(lambda p, v, w, t, ta: S._path(model, model.effects + (air,), p, v, w, t, ta)[0]))
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    pos = np.asarray(fly(f32(p0), f32(v0), f32(w0), f32(t0), f32(tau)), np.float64)
    pos = pos + rng.normal(0.0, noise, pos.shape)
    half = samples // 2
    for i in cut:
        pos[i, half:, 2] = 2.0 * pos[i, half - 1, 2] - pos[i, half:, 2]
    pad = lambda a: np.concatenate([a, np.repeat(a[-1:], rows - n, 0)])  # noqa: E731
    mask = np.zeros((rows, samples))
    mask[:n] = 1.0
    # the measured spin is the flight's mean; its change over 0.25 s is negligible here
    fl = Flights(t0=pad(t0), tau=pad(np.asarray(tau)), pos=pad(pos), mask=mask, spin=pad(w0),
                 session=np.zeros(rows, np.int64), segment_id=np.arange(rows), n=n)
    return Phases(flights=fl, table=None, racket=None, sessions=np.array([0]), skipped={})


def test_segment_offsets_measure_a_steady_wind(model):
    cls = fx.effect_class("air_flow")
    ph = _flights(model, _air(cls, wind=WIND), n=32, noise=0.0)
    pb = C.problem(ph, model)
    w, info, _ = segment_winds(model, (), (), (), pb.data["flight"], pb.x0)
    n = ph.flights.n
    # along the flight (x) the drag resolves the wind to millimetres per second without noise
    assert np.abs(w[:n, 0] - WIND[0]).max() < 0.02, w[:n, 0]
    assert abs(np.median(w[:n, 1]) - WIND[1]) < 0.02, w[:n, 1]
    eig = np.linalg.eigvalsh(info[:n])
    assert np.all(eig[:, -1] > 0), eig


#: Segments cut wrongly in the second set of flights (tens of millimetres RMS against one).
CUT = (5, 70, 140)


def _gusty(model, cut=()):
    cls = fx.effect_class("air_flow")
    air = _air(cls, wind=WIND, gust_amp=GUST_AMP, gust_freq=GUST_FREQ, gust_phase=GUST_PHASE)
    pb = C.problem(_flights(model, air, n=160, cut=cut), model)
    return pb, C.fit(pb, ["air_flow"], model, steps=40)


@pytest.fixture(scope="module")
def gusty(model):
    return _gusty(model)


@pytest.fixture(scope="module")
def gusty_cut(model):
    return _gusty(model, CUT)


@pytest.mark.parametrize("flights", ["gusty", "gusty_cut"])
def test_air_flow_candidate_finds_the_gusts_frequencies_and_amplitudes(flights, request):
    """Also where a few segments were cut wrongly: the robust loss keeps them from pulling the fit."""
    _, cand = request.getfixturevalue(flights)
    p = cand.params["air_flow"][0]
    freq, amp = np.asarray(p["gust_freq"]), np.linalg.norm(p["gust_amp"], axis=1)
    for f_true, a_true in zip(GUST_FREQ[:2], np.linalg.norm(GUST_AMP[:2], axis=1)):
        k = int(np.argmin(np.abs(freq - f_true) + (amp < 0.05)))
        assert abs(freq[k] - f_true) < 0.005 and abs(amp[k] - a_true) < 0.3 * a_true, (freq, amp)
    assert np.linalg.norm(np.asarray(p["wind"]) - WIND) < 0.08, p["wind"]


def test_the_gusts_lower_the_held_out_error_to_the_noise_beyond_a_steady_wind(gusty, model, monkeypatch):
    pb, cand = gusty
    h = cand.heldout["flight"]
    assert cand.significant, h
    # 1 mm per axis of noise leaves a 3-D residual of about sqrt(3 (1 - 6 / 78)) = 1.66 mm
    assert h["after_rms"] < 0.0017, h
    monkeypatch.setattr(C, "REFINE", {})  # the first descent alone: the steady wind
    steady = C.fit(pb, ["air_flow"], model, steps=40)
    assert not np.any(steady.params["air_flow"][0]["gust_amp"]), steady.params  # held at no gusts
    # which leaves 1.9 mm: the gusts' part above the noise
    assert h["after_rms"] < 0.92 * steady.heldout["flight"]["after_rms"], (h, steady.heldout)


def test_wrongly_cut_segments_do_not_spoil_the_fit_of_the_others(gusty_cut):
    """The held-out error of the segments cut right falls to the noise, as without the cut ones."""
    pb, cand = gusty_cut
    n = pb.data["flight"]["mask"].shape[0]
    keep = np.ones(n, bool)
    keep[list(CUT)] = False
    test = np.asarray(pb.data["flight"]["test"]) > 0
    sse, count = C.item_sums(pb, "flight", cand.errors["flight"])
    base, _ = C.item_sums(pb, "flight", pb.base["flight"])
    assert test[list(CUT)].any() and (~test[list(CUT)]).any(), test[list(CUT)]  # cut ones on both sides
    rows = test & keep
    rms = np.sqrt(sse[rows].sum() / count[rows].sum())
    assert rms < 0.0017 and rms < 0.8 * np.sqrt(base[rows].sum() / count[rows].sum()), rms


def test_the_descent_ends_with_every_segment_at_its_optimal_initial_state(gusty, model):
    """The descent refreshes the states' Jacobian only every few steps (``JACOBIAN_EVERY``, chord
    steps between): the errors it returns must still be those of each segment's best initial state
    for the fitted parameters, as six fresh Gauss-Newton steps from the model's states find it."""
    pb, cand = gusty
    assert C.JACOBIAN_EVERY > 1
    (spec,), consts = (cand.spec,), cand.consts
    u = jax.tree.map(jnp.asarray, cand.u)
    converged, _ = C.evaluate(model, (spec,), consts, u, pb, iterations=S.GN_START, phases=("flight",))
    sse, count = C.item_sums(pb, "flight", cand.errors["flight"])
    best, _ = C.item_sums(pb, "flight", converged["flight"])
    real = np.asarray(pb.data["flight"]["train"] + pb.data["flight"]["test"]) > 0
    rms, rms_best = np.sqrt(sse[real] / count[real]), np.sqrt(best[real] / count[real])
    # no segment is left above its optimum by more than a few micrometres (the noise is 1 mm)
    assert np.all(rms - rms_best < 5e-6), np.max(rms - rms_best)


def test_both_descents_of_air_flow_share_one_compiled_program():
    """The second descent (gusts free, per-session starts from the periodogram) has the first's
    static spec and the same shapes of constants, so it reuses the first's compiled program."""
    n = 3
    first, const = C.spec("air_flow")
    const = S.session_starts(first, const, n)
    start = {k: np.array(v) for k, v in const["start"].items()}
    start["gust_freq"][1] = [0.2, 0.4, 0.6]  # what a periodogram would set
    second, const2 = S.second_descent(first, start, SCALES)
    assert second == first and hash(second) == hash(first)
    shapes = lambda c: jax.tree.map(np.shape, c)  # noqa: E731
    assert shapes(const2) == shapes(const), (shapes(const2), shapes(const))
    # per session, the first descent starts where the catalogue's neutral values are
    assert np.all(const["start"]["gust_freq"] == 0.0) and const["start"]["wind"].shape == (n, 3)
