"""Diagnosis: the workflow that finds where simulation and measurement disagree and names the missing effect.

It uses :mod:`ddsgen.fit` (fitting, simulation, the ``compare`` gap); ``fit`` never imports it.
"""

from ddsgen.diagnose.loop import (
    BOOTSTRAP_QUANTILE,
    RULE,
    DiagnoseConfig,
    Diagnosis,
    Evaluation,
    bootstrap_fall,
    diagnose,
    relative_fall,
    replane,
)

__all__ = [
    "BOOTSTRAP_QUANTILE",
    "RULE",
    "DiagnoseConfig",
    "Diagnosis",
    "Evaluation",
    "bootstrap_fall",
    "diagnose",
    "relative_fall",
    "replane",
]
