"""The wheel works on its own (issue 13): built from a copy of the sources, installed into a
fresh virtual environment, run from a folder outside the repository.

The new environment borrows torch and the other heavy dependencies from the test environment
through a .pth line (installing them would take minutes), but ddsgen itself comes only from
the wheel: the test asserts ``ddsgen.__file__`` lies inside the new environment, so the
editable install of the test environment cannot stand in for it. The render must give the
same bytes as the editable install for the same seed, put its compiled kernel in the user's
cache directory, and write nothing into the current folder (except ``o/``) or site-packages.
"""

from __future__ import annotations

import os
import shutil
import site
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SOURCES = ("ddsgen", "presets", "pattern_assets", "pyproject.toml", "setup.py", "README.md")
RENDER = ["render", "kinect_v1", "-n", "2", "--out", "o", "--workers", "1", "--seed", "0"]


def _run(args, cwd, env, timeout=600) -> subprocess.CompletedProcess:
    result = subprocess.run([str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, f"{' '.join(map(str, args))} failed:\n{result.stdout}\n{result.stderr}"
    return result


def _tree(folder: Path) -> dict[str, bytes]:
    """Relative path -> bytes of every file under ``folder``."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The ddsgen wheel, built from a copy of the sources (no build/ or egg-info in the checkout)."""
    root = tmp_path_factory.mktemp("wheel")
    src = root / "src"
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            src.mkdir(exist_ok=True)
            shutil.copy2(REPO / name, src / name)
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-w", root / "dist",
          src], cwd=root, env=dict(os.environ))  # fmt: skip
    (built,) = (root / "dist").glob("ddsgen-*.whl")
    return built


def test_wheel_ships_every_preset_pattern_and_the_kernel_source(wheel):
    import zipfile

    names = set(zipfile.ZipFile(wheel).namelist())
    for folder, package in (("presets", "ddsgen/presets"), ("pattern_assets", "ddsgen/pattern_assets")):
        shipped = sorted(p.name for p in (REPO / folder).iterdir() if p.suffix in (".yaml", ".png"))
        assert shipped, folder
        missing = [name for name in shipped if f"{package}/{name}" not in names]
        assert not missing, f"not in the wheel: {missing}"
    assert {"ddsgen/sensor/matcher/csrc/zncc.c", "ddsgen/csrc/raster.c", "ddsgen/csrc/registration.c"} <= names
    assert not any(name.startswith(("presets/", "pattern_assets/", "tests/")) for name in names)


@pytest.mark.slow
def test_wheel_install_renders_from_any_folder_like_the_editable_install(wheel, tmp_path):
    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", venv], cwd=tmp_path, env=dict(os.environ))
    python = venv / "bin" / "python"
    # pip of the test environment installs into the new one; before the .pth exists, so it
    # sees no ddsgen there and installs the wheel's files.
    _run([sys.executable, "-m", "pip", "--python", python, "install", "--no-deps", "--no-index", "-q", wheel],
         cwd=tmp_path, env=dict(os.environ))  # fmt: skip
    new_site = Path(_run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], tmp_path,
                         dict(os.environ)).stdout.strip())  # fmt: skip
    # torch & co. from the test environment: appended to sys.path, after the new site-packages.
    # (.pth files in a folder named by a .pth line are not run, so the editable finder stays off.)
    (new_site / "borrowed_dependencies.pth").write_text(
        "\n".join([sysconfig.get_paths()["purelib"], *site.getsitepackages()]) + "\n"
    )
    before = _tree(new_site)

    env = {k: v for k, v in os.environ.items() if not k.startswith(("DDSGEN_", "PYTHON", "VIRTUAL_ENV"))}
    env.update(XDG_CACHE_HOME=str(tmp_path / "user_cache"), DDSGEN_NO_COMPILE="1", OMP_NUM_THREADS="1")
    where = _run([python, "-c", "import ddsgen; print(ddsgen.__file__)"], tmp_path, env).stdout.strip()
    assert Path(where).is_relative_to(new_site), f"ddsgen imported from {where}, not from the wheel"

    work = tmp_path / "work"  # outside the repository
    work.mkdir()
    _run([venv / "bin" / "ddsgen", *RENDER], work, env)
    listing = _run([venv / "bin" / "ddsgen", "presets"], work, env).stdout
    assert sorted(p.name for p in work.iterdir()) == ["o"], "nothing but the output folder in the current folder"
    lines = {line.split()[0]: line for line in listing.splitlines()}
    assert "640x480" in lines["kinect_v1"] and "0.4-10 m" in lines["kinect_v1"]
    assert str(new_site) in listing.splitlines()[-1], "the listed presets are the wheel's"

    for stem in ("zncc", "raster", "registration"):  # the matcher's kernels, the ray-cast raster, the registration maps
        kernels = list((tmp_path / "user_cache" / "ddsgen").glob(f"*/kernels/{stem}_*.so"))
        assert len(kernels) == 1, f"the C kernel {stem} is compiled into the user's cache directory"
    assert _tree(new_site) == before, "nothing written into site-packages"

    reference = tmp_path / "editable"
    reference.mkdir()
    _run([Path(sys.executable).parent / "ddsgen", *RENDER], reference, env)
    ours, theirs = _tree(work / "o"), _tree(reference / "o")
    assert sorted(ours) == sorted(theirs)
    assert len([name for name in ours if name.startswith("depth/") and name.endswith(".png")]) == 2
    for name in ours:  # sensor.yaml included: it names a shipped preset by name, not by its installed path
        assert ours[name] == theirs[name], f"{name} differs between the wheel and the editable install"
