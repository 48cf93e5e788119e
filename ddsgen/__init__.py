"""ddsgen: synthetic structured-light depth datasets from a differentiable sensor simulation.

Data flows one way: cli -> runner -> scene -> raycast -> sensor -> io.
"""

import os as _os

# numpy's OpenBLAS would run the ray caster's small 3-vector products on every core and
# spin-wait between them: 2x the CPU for the same wall time (measured: 75 ms wall, 150 ms
# CPU per ray cast), which starves the other render workers. Our parallelism is over frames.
# Must be set before numpy loads; a value the user chose is kept.
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

__version__ = "0.1.0"
