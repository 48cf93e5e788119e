"""Unpaired fit: tune the sensor to a folder of plain real depth images (no poses, no meshes).

    real folder (depth PNG/EXR) ──► patch features ─┐
                                                     ├─► distance ─► 1-D searches ─► fitted preset
    scene list ─► ray cast once ─► DepthSensor ─► patch features ─┘            └─► bootstrap uncertainties

Modules: :mod:`.realfolder` (read any folder of depth images), :mod:`.features`
(scene-independent patch features, pooled per frame so frames can be resampled),
:mod:`.parameters` (the table of fitted preset keys), :mod:`.search` (rendering and the
fitting loop), :mod:`.report` (plots, JSON). Why a feature distance and not a
discriminator: docs/unpaired_fit.md.
"""
