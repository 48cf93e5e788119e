"""ddsgen: synthetic structured-light depth datasets from a differentiable sensor simulation.

Data flows one way: cli -> runner -> scene -> raycast -> sensor -> io.
"""

__version__ = "0.1.0"
