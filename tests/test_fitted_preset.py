"""The preset fit, fit --unpaired and diagnose --apply write: the user's preset with the changed keys, loadable from
any folder with the same files it named."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np

from ddsgen.fit.fitted_preset import assemble_preset, write_preset
from ddsgen.preset import PATTERN_DIR, load_preset


def _user_preset(folder: Path, pattern_name: str) -> Path:
    """kinect_v1 copied into ``folder`` naming a dot pattern of its own, saved there as ``pattern_name``."""
    folder.mkdir(parents=True)
    stock = load_preset("kinect_v1")
    shipped = cv2.imread(str(Path(PATTERN_DIR) / stock.pattern), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(folder / pattern_name), np.ascontiguousarray(shipped[:, ::-1]))  # another pattern
    path = folder / "mine.yaml"
    write_preset(stock.replace(pattern=pattern_name, name="mine"), path, "the user's own pattern")
    return path


def test_a_pattern_of_the_users_folder_stays_that_pattern_even_when_named_like_a_shipped_one(tmp_path):
    stock_name = load_preset("kinect_v1").pattern
    original = load_preset(_user_preset(tmp_path / "mine", stock_name))
    mine = original.resolve_path(original.pattern).resolve()
    assert mine.parent == (tmp_path / "mine").resolve()

    out = write_preset(assemble_preset(original, {"baseline_m": 0.076}, "fitted"), tmp_path / "elsewhere" / "f.yaml", "")
    fitted = load_preset(out)
    assert fitted.resolve_path(fitted.pattern).resolve() == mine  # not the shipped pattern of that name
    assert fitted.baseline_m == 0.076 and fitted.name == "mine_fitted"


def test_a_shipped_pattern_keeps_its_bare_name(tmp_path):
    stock = load_preset("kinect_v1")
    fitted = assemble_preset(stock, {}, "unpaired")
    assert fitted.pattern == stock.pattern and fitted.name == "kinect_v1_unpaired"
    out = write_preset(fitted, tmp_path / "f.yaml", "")
    assert load_preset(out).resolve_path(stock.pattern).parent.resolve() == Path(PATTERN_DIR).resolve()


def test_changed_files_win_over_the_originals(tmp_path):
    folder = tmp_path / "mine"
    original = load_preset(_user_preset(folder, "dots.png"))
    shutil.copy(folder / "dots.png", tmp_path / "other.png")
    fitted = assemble_preset(original, {"pattern": str(tmp_path / "other.png")}, "fitted")
    assert fitted.pattern == str(tmp_path / "other.png")
