"""Unpaired fit: tune the sensor to a folder of plain real depth images (no poses, no meshes).

    real folder (PNG / EXR) ──────────────────────────────► patch features ─┐
    scene list ─► ray cast once ─► DepthSensor(values) ─► patch features ─┴─► distance
    distance ─► coordinate searches over the table ─► fitted values ± bootstrap uncertainty

Modules: :mod:`.realfolder` (read any folder of depth images), :mod:`.features`
(scene-independent patch features, pooled per frame so frames can be resampled),
:mod:`.parameters` (the table of fitted preset keys), :mod:`.search` (rendering and the
fitting loop), :mod:`.report` (plots, JSON). Why a feature distance and not a
discriminator: docs/validation.md.
"""
