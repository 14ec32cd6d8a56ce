"""The reality generator: synthetic measured data with a known truth.

Games between a robot (at the +x end by default) and an opponent are simulated with a *truth
model*: ``conti2026`` plus a chosen set of effects from :mod:`ttsim_jax.effects` (each switchable
by name, parameterised, drawn once per dataset or once per game). The result is a
:class:`~ttsim_jax.data.Dataset` in the measured-data format, written with the ground truth next
to it, so that fitting, evaluation and the sim-to-real gap diagnosis can be checked against
known answers.

How a game is made:

* A rally starts with the server's toss (an ``other`` event: the ball leaves the hand), then the
  serve, a racket contact on the falling ball. Every racket contact is made by inverting the
  contact model: the hitter picks a shot (serve, topspin or backspin drive, push, block, smash,
  lob; the ranges of :data:`ttsim_jax.shots.SHOT_TYPES`, up to 35 m/s and 1000 rad/s) suited to
  where the ball is, aims it through the flight model (Newton iterations on heading and vertical
  speed so that the aimed bounce lands on the target), and solves for the racket state that
  produces that outgoing ball with the *plain* model: face normal, then normal racket speed from
  the restitution law, then tangential racket speed from the grip law (exact for the plain
  model). The racket face is placed at the ball with the contact point d sampled over the face
  (most hits near the centre, some in every band 0-5, 5-8 and beyond 8 cm). The *true* contact
  (truth model, with its effects) then decides what the ball really does.
* Flights are simulated with :func:`ttsim_jax.kernel.simulate` (dt = 1 ms, RK4), every game in its
  own lane of one batch (each lane with its game's truth model: ``model_axes=0``), in chunks of
  ``chunk_steps`` steps recorded at every step (so that contacts can be placed on the 1 ms grid,
  between the 200 Hz frames); the host reads the event log and trajectory of each chunk, decides
  hits and ends of rallies, and restarts each lane from its new state. A ball is hit after it
  bounced on the receiver's half, when it reaches the receiver's hitting distance (sampled per
  shot) or falls low. A rally ends when a ball hits the net, misses
  the table, bounces on the wrong half, or after a sampled number of shots (the receiver misses);
  the ball is then followed until it hits the floor (``out``).
* Observations are the ball centre at 200 Hz (every ``obs_every`` steps of a session clock; racket
  contacts fall between frames). The robot's racket contacts are ``racket`` events with a racket
  state; the opponent's contacts and the tosses are ``other`` events (no racket state).
  Effects acting on the record (racket-state error, position noise, spin-estimate noise with
  confidences and outliers, missing frames, the tracker's clock rate and latency, a camera
  scale error) are applied to what is written, never to the truth: the truth tables keep the
  true positions and the true session clock's times.
* Segments are derived from the events; each segment's spin is a measurement of the mean true
  spin over its samples (with :class:`~ttsim_jax.effects.SpinNoise` if enabled, else exact with
  confidence 1), and its samples carry the same spin.

Everything is deterministic for a seed and a configuration: every game has its own random
streams (``numpy`` generators seeded by (seed, stream, game)).

Modules: ``config`` (what to generate: :class:`GeneratorConfig`, presets, TOML files), ``game``
(the rallies), ``strokes`` (shot choice, contact points, aiming), ``inversion`` (racket states that
play an aimed ball), ``assembly`` (the dataset and its truth), ``generation`` (:func:`generate`,
:func:`rerecord`), ``truth`` (the truth files: :func:`write`, :func:`load_truth`) and
``synthetic`` (a small dataset of racket contacts with known states).

Main entry points::

    from ttsim_jax.reality import generate, make_config, write, load_truth
"""

from ttsim_jax.lazy import exports

_NAMES = {
    **dict.fromkeys(["BYTES_PER_ROW", "PRESETS", "GeneratorConfig", "GeneratorError", "config_from_toml", "make_config",
                     "memory_bytes"], "ttsim_jax.reality.config"),
    **dict.fromkeys(["invert_contact"], "ttsim_jax.reality.inversion"),
    **dict.fromkeys(["sample_contact_points"], "ttsim_jax.reality.strokes"),
    **dict.fromkeys(["GENERATOR_VERSION", "Generated"], "ttsim_jax.reality.assembly"),
    **dict.fromkeys(["generate", "rerecord"], "ttsim_jax.reality.generation"),
    **dict.fromkeys(["Truth", "load_truth", "write"], "ttsim_jax.reality.truth"),
    **dict.fromkeys(["synthetic_contact_dataset", "synthetic_rig_dataset"], "ttsim_jax.reality.synthetic"),
}
__getattr__, __dir__ = exports(__name__, _NAMES)
__all__ = sorted(_NAMES)
