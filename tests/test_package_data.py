"""Presets, pattern assets and the cache folder as an installed package finds them (issue 13):
presets by name from any folder, a user's preset resolving its pattern beside itself first and
then among the shipped patterns, ``ddsgen presets``, and the cache in the user's cache directory.
(tests/test_wheel.py checks the same from a real wheel install.)"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from ddsgen import __version__
from ddsgen.cache import cache_dir
from ddsgen.cli import main
from ddsgen.errors import InputError
from ddsgen.preset import PATTERN_DIR, PRESET_DIR, load_preset, shipped_preset_names

REPO = Path(__file__).resolve().parents[1]


def test_every_preset_in_the_presets_folder_loads_by_name_from_another_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    in_repo = sorted(p.stem for p in (REPO / "presets").glob("*.yaml"))
    assert shipped_preset_names() == in_repo
    for name in in_repo:
        preset = load_preset(name)
        assert Path(preset.source) == Path(PRESET_DIR / f"{name}.yaml")
        assert load_preset(f"{name}.yaml") == preset
        pattern = preset.resolve_path(preset.pattern)
        assert pattern.is_file() and pattern.parent == Path(PATTERN_DIR), f"{name}: {pattern}"


def test_an_existing_file_is_read_as_a_file_and_a_bare_name_is_the_shipped_preset(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    text = (REPO / "presets" / "kinect_v1.yaml").read_text().replace("baseline_m: 0.075", "baseline_m: 0.08")
    assert "baseline_m: 0.08" in text
    Path("kinect_v1.yaml").write_text(text)
    assert load_preset("kinect_v1.yaml").baseline_m == pytest.approx(0.08)
    assert load_preset("kinect_v1").baseline_m == pytest.approx(0.075)  # no file called "kinect_v1" here


def test_unknown_preset_name_is_one_line_naming_the_shipped_ones(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError, match="kinect_v9: preset file not found.*kinect_v1"):
        load_preset("kinect_v9")
    assert main(["render", "kinect_v9", "-n", "1", "--out", "o"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "kinect_v1" in err and "matterport_pro2" in err
    assert not Path("o").exists()


def test_user_preset_finds_its_pattern_beside_itself_first_then_among_the_shipped_ones(tmp_path):
    mine = tmp_path / "mine" / "sensor.yaml"
    mine.parent.mkdir()
    shutil.copy(REPO / "presets" / "kinect_v1.yaml", mine)
    preset = load_preset(mine)
    shipped = Path(PATTERN_DIR / preset.pattern)
    assert preset.resolve_path(preset.pattern) == shipped
    local = mine.parent / preset.pattern
    shutil.copy(shipped, local)
    assert preset.resolve_path(preset.pattern) == local
    assert preset.resolve_path("nowhere.png") == mine.parent / "nowhere.png"  # named in the error message


def test_presets_command_lists_one_line_per_shipped_preset(capsys):
    assert main(["presets"]) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = {line.split()[0]: line for line in lines[1:-1]}
    assert sorted(rows) == shipped_preset_names()
    kinect = rows["kinect_v1"]
    assert "640x480" in kinect and "0.4-10 m" in kinect and "b 75 mm" in kinect
    assert kinect.rstrip().endswith("Kinect V1 as the device measures")  # the file's first comment line
    assert "1280x1024" in rows["matterport_pro2"]


def test_presets_command_prints_a_preset_that_loads_as_a_user_file(tmp_path, capsys):
    assert main(["presets", "matterport_pro2"]) == 0
    copy = tmp_path / "my_sensor.yaml"
    copy.write_text(capsys.readouterr().out)
    mine, shipped = load_preset(copy), load_preset("matterport_pro2")
    assert mine.to_dict() == shipped.to_dict()
    assert mine.resolve_path(mine.pattern) == shipped.resolve_path(shipped.pattern)
    assert main(["presets", "nope"]) == 2


def test_cache_is_in_the_user_cache_dir_per_version_unless_ddsgen_cache_dir_is_set(tmp_path, monkeypatch):
    monkeypatch.delenv("DDSGEN_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_dir() == tmp_path / "xdg" / "ddsgen" / __version__
    assert cache_dir().is_dir()
    monkeypatch.setenv("DDSGEN_CACHE_DIR", str(tmp_path / "mine"))
    assert cache_dir() == tmp_path / "mine" and cache_dir().is_dir()


def test_no_module_finds_its_data_relative_to_its_own_file():
    """Package data through importlib.resources only: a path built from __file__ breaks in a
    wheel as soon as a file moves (this is how issue 13's "preset file not found" came about)."""
    offenders = [str(p.relative_to(REPO)) for p in (REPO / "ddsgen").rglob("*.py") if "__file__" in p.read_text()]
    assert offenders == []
