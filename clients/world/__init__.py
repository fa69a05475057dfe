"""Synthetic worlds for evaluating visual localisation.

A world is generated from a seed: a procedural scene of textured quads (a street block
for a ground robot as in Weiss et al. 2008, or open land for a UAV as in Erhard et al.'s
Flyphone), a route through it, and several traversals of that route under different
illumination (``sunny``, ``cloudy``, ``dusk``), rendered with an exact pinhole camera and
written as a data set folder of EXIF-geotagged JPEGs with a ground-truth CSV.

>>> from clients.world import generate_world
>>> info = generate_world("out", kind="robot", seed=1, passes=["sunny", "cloudy"])  # doctest: +SKIP

See :mod:`clients.world.writer` for the folder layout and the GPS-noise convention.
"""

from vloc.clients.world.lighting import ILLUMINATIONS, Illumination
from vloc.clients.world.writer import DEFAULT_ORIGIN, KINDS, WorldInfo, generate_world

__all__ = ["DEFAULT_ORIGIN", "ILLUMINATIONS", "KINDS", "Illumination", "WorldInfo",
           "generate_world"]
