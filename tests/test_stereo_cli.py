"""``ddsgen stereo LEFT RIGHT``: round trip on a small synthetic rectified pair, bad input."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ddsgen.cli import main
from ddsgen.io.exr import read_exr


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """A textured rectified pair with a fronto-parallel plate (d = 12 px) in front of a
    background (d = 5 px). Left pixel u sees the right image at u - d."""
    folder = tmp_path_factory.mktemp("pair")
    rng = np.random.default_rng(0)
    height, width = 60, 120
    texture = cv2.GaussianBlur(rng.random((height, width + 40)).astype(np.float32), (0, 0), 0.8)
    disparity = np.full((height, width), 5.0, np.float32)
    disparity[15:45, 40:90] = 12.0
    u = np.arange(width)[None, :] + 20  # texture column of right-image pixel 0 is 20
    right = texture[:, 20 : 20 + width]
    left = np.take_along_axis(texture, (u - disparity).astype(np.int64), axis=1)
    to8 = lambda a: np.clip((a - a.min()) / (a.max() - a.min()) * 255, 0, 255).astype(np.uint8)  # noqa: E731
    left_path, right_path = folder / "left.png", folder / "right.png"
    cv2.imwrite(str(left_path), cv2.cvtColor(to8(left), cv2.COLOR_GRAY2BGR))  # colour input is accepted
    cv2.imwrite(str(right_path), to8(right))
    return left_path, right_path, disparity


def test_round_trip_writes_float32_disparity_exr_and_png(pair, tmp_path, capsys):
    left, right, truth = pair
    out, png = tmp_path / "disp.exr", tmp_path / "vis.png"
    code = main(["stereo", str(left), str(right), "--max-disparity", "20", "--block", "7", "--out", str(out), "--png", str(png)])
    assert code == 0
    assert "valid" in capsys.readouterr().out
    disparity = read_exr(out)
    assert disparity.dtype == np.float32 and disparity.shape == truth.shape
    valid = disparity > 0
    inner = np.zeros_like(valid)
    inner[4:-4, 25:-4] = True  # left columns < d_max + window see outside the right image
    # away from the plate's edges (window fattening), the disparity is right within 1/4 px
    edges = cv2.dilate((np.abs(np.gradient(truth, axis=1)) + np.abs(np.gradient(truth, axis=0)) > 0).astype(np.uint8), np.ones((9, 9)))
    check = inner & ~edges.astype(bool)
    assert valid[check].mean() > 0.95
    assert np.mean(np.abs(disparity - truth)[check & valid] <= 0.25) > 0.95
    image = cv2.imread(str(png))
    assert image is not None and image.shape[:2] == truth.shape
    assert not list(tmp_path.glob(".*tmp*")), "temporary files left behind"


def test_unreadable_image_is_one_line_exit_2(pair, tmp_path, capsys):
    left, _, _ = pair
    bogus = tmp_path / "bogus.png"
    bogus.write_text("not an image")
    out = tmp_path / "disp.exr"
    code = main(["stereo", str(left), str(bogus), "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err.count("\n") == 0 and f"{bogus}: cannot read image" in err
    assert not out.exists()
    assert main(["stereo", str(tmp_path / "missing.png"), str(left)]) == 2


@pytest.mark.parametrize(
    "args, message",
    [
        (["--block", "4"], "--block"),
        (["--max-disparity", "500"], "--max-disparity"),
        (["--min-disparity", "-1"], "--min-disparity"),
    ],
)
def test_bad_options_exit_2(pair, tmp_path, capsys, args, message):
    left, right, _ = pair
    out = tmp_path / "disp.exr"
    assert main(["stereo", str(left), str(right), "--out", str(out), *args]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_size_mismatch_exit_2(pair, tmp_path, capsys):
    left, _, _ = pair
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((10, 10), np.uint8))
    assert main(["stereo", str(left), str(small), "--out", str(tmp_path / "d.exr")]) == 2
    assert "differs" in capsys.readouterr().err
