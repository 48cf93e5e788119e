"""Comparing the simulated sensor with real scans, and fitting it to them (issue 3)."""
