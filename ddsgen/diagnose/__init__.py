"""Diagnosis: the workflow that finds where simulation and measurement disagree and names the missing effect.

It uses :mod:`ddsgen.fit` (fitting, simulation, the ``compare`` gap); ``fit`` never imports it.

Modules, in the order the loop uses them:

* :mod:`~ddsgen.diagnose.loop` -- :func:`diagnose`, the loop itself, and its settings;
* :mod:`~ddsgen.diagnose.plane` -- the support plane re-estimated under each model;
* :mod:`~ddsgen.diagnose.evaluation` -- gap and noise floor of a model on frames;
* :mod:`~ddsgen.diagnose.residuals` -- residual binned along physical axes, structure beyond noise;
* :mod:`~ddsgen.diagnose.candidates` -- each library effect added and its parameters searched;
* :mod:`~ddsgen.diagnose.acceptance` -- the credited fall and the rule that accepts a candidate;
* :mod:`~ddsgen.diagnose.stage_cache` -- the sensors' matches and front ends reused while their inputs are unchanged;
* :mod:`~ddsgen.diagnose.results` -- steps, candidates, ``diagnosis.json``;
* :mod:`~ddsgen.diagnose.sentences` -- the sentences that name an accepted effect, and the log's summaries;
* :mod:`~ddsgen.diagnose.maps` -- full-resolution residual maps of held-out frames, for the report;
* :mod:`~ddsgen.diagnose.report` -- ``diagnosis.json``, ``report.html`` and its PNG figures written to a folder.
"""

from ddsgen.diagnose.acceptance import BOOTSTRAP_QUANTILE, RULE, bootstrap_fall, relative_fall
from ddsgen.diagnose.evaluation import Evaluation
from ddsgen.diagnose.config import DiagnoseConfig
from ddsgen.diagnose.loop import diagnose
from ddsgen.diagnose.plane import replane
from ddsgen.diagnose.results import Diagnosis

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
