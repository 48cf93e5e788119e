"""Package layout only (metadata and dependencies are in pyproject.toml).

The repository keeps presets/ and pattern_assets/ at its root (``ddsgen render
presets/kinect_v1.yaml`` in a checkout); the wheel ships the same folders as the packages
``ddsgen.presets`` and ``ddsgen.pattern_assets`` (read with importlib.resources). Their
package-data globs in pyproject.toml take every preset and pattern added later.
"""

from setuptools import find_namespace_packages, setup

ASSET_PACKAGES = {"ddsgen.presets": "presets", "ddsgen.pattern_assets": "pattern_assets"}

setup(packages=find_namespace_packages(include=["ddsgen", "ddsgen.*"]) + list(ASSET_PACKAGES), package_dir=ASSET_PACKAGES)
