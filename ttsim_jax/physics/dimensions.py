"""The regulation (ITTF) table: its dimensions, named once.

The world frame has its origin at the centre of the playing surface, x along the table's length, y
across it and z up; the surface is z = 0 and the net stands at x = 0. These are the defaults of a
model's ``[table.geometry]`` (:mod:`ttsim_jax.params`) and the frame of the measured-data format
(:mod:`ttsim_jax.data.schema`); a model may set other dimensions.
"""

from __future__ import annotations

#: Length (along x) and width (along y) of the playing surface [m].
TABLE_LENGTH = 2.74
TABLE_WIDTH = 1.525
#: Height of the net's top above the playing surface, and how far its posts stand outside the
#: side lines [m].
NET_HEIGHT = 0.1525
NET_OVERHANG = 0.1525
#: Height of the floor in the world frame [m]: the playing surface is 0.76 m above it.
FLOOR_Z = -0.76
#: Half length and half width of the playing surface [m].
TABLE_HALF_LENGTH = TABLE_LENGTH / 2
TABLE_HALF_WIDTH = TABLE_WIDTH / 2
