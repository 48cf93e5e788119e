"""Fitting the simulated sensor to real scans: paired (against their annotated scenes) and unpaired (fit --unpaired)."""

#: Tile side (px) of the Adam steps of ``ddsgen fit`` and of a diagnosis' base fit and refits
#: (:mod:`ddsgen.fit.tiles`). Here, not in tiles.py, so that the commands can show it without importing torch code.
DEFAULT_TILE_PX = 192
