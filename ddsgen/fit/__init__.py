"""Comparing the simulated sensor with real scans, and fitting it to them (issue 3)."""

#: Tile side (px) of the Adam steps of ``ddsgen fit`` and of a diagnosis' base fit and refits
#: (:mod:`ddsgen.fit.tiles`). Here, not in tiles.py, so that the commands can show it without importing torch code.
DEFAULT_TILE_PX = 192
