"""fit --unpaired is judged on real frames it did not see: held out by sequence, and a fit that is not closer to them
than the input is not written (ddsgen.fit.unpaired.holdout)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from ddsgen.fit.unpaired.holdout import judge, split_frames


def test_several_sequences_are_held_out_whole_and_one_sequence_frame_by_frame():
    names = [f"seq{s}/depth/{i:06d}.png" for s in (1, 2, 3) for i in range(3)]
    fit, held, kind = split_frames(names, seed=0)
    assert kind == "sequence" and len(held) == 3 and len(fit) == 6
    held_sequences = {names[i].split("/")[0] for i in held}
    assert len(held_sequences) == 1 and not held_sequences & {names[i].split("/")[0] for i in fit}
    fit, held, kind = split_frames([f"{i}.png" for i in range(5)], seed=0)
    assert kind == "frame" and fit == [0, 2, 4] and held == [1, 3]
    assert split_frames(["only.png"], seed=0) == ([0], [], "none")


def test_the_judgement_compares_the_held_out_frames_with_each_presets_renders():
    from ddsgen.fit.unpaired.features import frame_features

    rng = np.random.default_rng(0)
    fb = 572.41 * 0.075

    def plane_frames(sigma_px: float, n: int = 2) -> list:  # a tilted plane, disparity noise sigma_px, 1/8 px steps
        v, u = np.mgrid[0:240, 0:320]
        disparity = fb / (1.0 + 0.002 * u + 0.001 * v) + rng.normal(0.0, sigma_px, (240, 320))
        return [frame_features((fb / (np.round(disparity * 8) / 8)).astype(np.float32), fb) for _ in range(n)]

    real, near, far = plane_frames(0.08), plane_frames(0.08), plane_frames(0.3)
    verdict = judge(real, stock_features=far, fitted_features=near)
    assert verdict["fitted_better"] and verdict["fitted"] < verdict["stock"]
    assert not judge(real, stock_features=near, fitted_features=far)["fitted_better"]
    assert judge([], near, far) == {"stock": None, "fitted": None, "fitted_better": False, "terms": {}}
    assert verdict["terms"]["fitted"]["noise"] < verdict["terms"]["stock"]["noise"]  # the noise is what differs
    assert verdict["groups"]["noise"] == "closer" and verdict["farther"] == []


def test_a_fit_closer_in_total_but_farther_beyond_the_spread_in_one_group_is_not_written():
    """The fitted renders match the held-out frames' noise (the total falls) but drop 0.2 % of their pixels where
    the frames drop none, in every frame: the holes group is farther by far more than the frames' spread, so the
    judgement keeps the input, and says which group stood against it. The same dropouts in only one frame of four
    are within the spread: a group that one frame moves does not stop a fit."""
    from ddsgen.fit.unpaired.features import frame_features

    rng = np.random.default_rng(1)
    fb = 572.41 * 0.075
    v, u = np.mgrid[0:240, 0:320]

    def plane(sigma_px: float, dropout_share: float = 0.0) -> dict:  # a tilted plane; dropouts of single pixels
        disparity = fb / (1.0 + 0.002 * u + 0.001 * v) + rng.normal(0.0, sigma_px, (240, 320))
        depth = (fb / (np.round(disparity * 8) / 8)).astype(np.float32)
        depth[rng.random(depth.shape) < dropout_share] = 0.0
        return frame_features(depth, fb)

    real = [plane(0.08) for _ in range(4)]
    stock = [plane(0.3) for _ in range(4)]
    fitted = [plane(0.08, 0.002) for _ in range(4)]
    verdict = judge(real, stock, fitted)
    assert verdict["fitted"] < verdict["stock"]  # closer in total: the noise gain outweighs the holes
    assert verdict["groups"]["holes"] == "farther" and verdict["farther"] == ["holes"]
    assert not verdict["fitted_better"]
    assert verdict["terms"]["fitted"]["holes"] - verdict["terms"]["stock"]["holes"] > 3 * verdict["spread"]["holes"]
    once = [plane(0.08, 0.002), plane(0.08), plane(0.08), plane(0.08)]
    verdict = judge(real, stock, once)
    assert verdict["groups"]["holes"] == "within noise" and verdict["fitted_better"]


@pytest.fixture(scope="module")
def small_real_folder(tmp_path_factory):
    """Six 160x120 frames of kinect_v1's own renders in two sequences, and the preset."""
    from ddsgen.fit.unpaired.search import camera_for, cast_scenes, render_depths
    from ddsgen.io.png import write_depth_png
    from ddsgen.preset import load_preset, save_preset
    from ddsgen.realscan.realfolder import round_like
    from ddsgen.scene.scenelist import load_scene_list

    folder = tmp_path_factory.mktemp("unpaired_holdout")
    stock = camera_for(load_preset("kinect_v1"), 160, 120)
    depths = render_depths(stock, cast_scenes(stock, load_scene_list(None), 6, seed=31), seed=31)
    for i, depth in enumerate(depths):
        write_depth_png(folder / "real" / f"seq{i % 2 + 1}" / f"{i:06d}.png", round_like(depth, 0.001))
    save_preset(stock, folder / "stock.yaml")
    return folder


def test_a_fit_that_is_not_closer_to_the_held_out_frames_writes_the_input(small_real_folder, tmp_path, monkeypatch,
                                                                          capsys):  # fmt: skip
    """A fit that lands far off (a 1/2 px disparity quantum where the frames show kinect_v1's 1/8 px) renders
    farther from the held-out sequence than the input: the written preset keeps every value of the input, and the
    terminal and the preset's header say so."""
    from ddsgen.cli import main
    from ddsgen.fit.unpaired import run
    from ddsgen.preset import load_preset

    real_fit = run.fit_unpaired

    def far_off(preset, *args, **kwargs):
        result = real_fit(preset, *args, **kwargs)
        return dataclasses.replace(result, after={"subpixel_level": 1})

    monkeypatch.setattr(run, "fit_unpaired", far_off)
    out = tmp_path / "fitted.yaml"
    assert main(["fit", str(small_real_folder / "stock.yaml"), str(small_real_folder / "real"), "--unpaired",
                 "--params", "subpixel_level", "--out", str(out), "--quiet",
                 "--report", str(tmp_path / "report")]) == 0  # fmt: skip
    report = json.loads((tmp_path / "report" / "unpaired_report.json").read_text())
    held = report["held_out"]
    assert held["kind"] == "sequence" and held["fitted"] > held["stock"] and report["written"] == "input"
    stock, written = load_preset(str(small_real_folder / "stock.yaml")), load_preset(str(out))
    assert {k: v for k, v in dataclasses.asdict(written).items() if k not in ("name", "source")} == \
        {k: v for k, v in dataclasses.asdict(stock).items() if k not in ("name", "source")}  # fmt: skip
    assert "the input's values, kept" in out.read_text()
    index = (tmp_path / "report" / "index.html").read_text()
    assert "feature distance on the held-out frames" in index and "profiles.png" in index
    assert "input preset's values are written, unchanged" in capsys.readouterr().out


def test_the_camera_of_a_folder_is_given_and_kept(small_real_folder, tmp_path):
    """--camera replaces the preset's camera (in px of the frames' size) and the written preset keeps it in its own
    pixels, whichever preset is written; a bad camera or one without --unpaired is one line and exit 2."""
    from ddsgen.cli import main
    from ddsgen.preset import load_preset

    out = tmp_path / "fitted.yaml"
    assert main(["fit", str(small_real_folder / "stock.yaml"), str(small_real_folder / "real"), "--unpaired",
                 "--params", "subpixel_level", "--camera", "150,151,80,60", "--out", str(out), "--quiet",
                 "--report", str(tmp_path / "report")]) == 0  # fmt: skip
    written = load_preset(str(out))
    assert (written.focal_px, written.focal_y_px, written.cx_px, written.cy_px) == pytest.approx((150, 151, 80, 60))
    report = json.loads((tmp_path / "report" / "unpaired_report.json").read_text())
    assert report["assumed_intrinsics"]["fx"] == pytest.approx(150)
    for bad in (["--camera", "150,151,80"], ["--camera", "150,151,500,60"]):
        assert main(["fit", str(small_real_folder / "stock.yaml"), str(small_real_folder / "real"), "--unpaired",
                     *bad, "--out", str(tmp_path / "bad.yaml"), "--quiet"]) == 2  # fmt: skip
    assert main(["fit", str(small_real_folder / "stock.yaml"), str(small_real_folder / "real"), "--camera",
                 "150,151,80,60", "--out", str(tmp_path / "bad.yaml"), "--quiet"]) == 2  # fmt: skip
    assert not (tmp_path / "bad.yaml").exists()


def test_the_camera_is_read_from_a_bop_file_given_or_found_in_the_folder(small_real_folder, tmp_path, capsys):
    """--camera FILE reads a BOP camera.json; without --camera the sequences' own scene_camera.json are used (they
    agree), with their depth scale, and the terminal says where the camera came from; images whose cameras or depth
    scales differ are refused in one line with exit 2 and nothing written."""
    import shutil

    from ddsgen.cli import main
    from ddsgen.preset import load_preset

    stock = tmp_path / "stock.yaml"
    shutil.copy(small_real_folder / "stock.yaml", stock)
    args = ["--unpaired", "--params", "subpixel_level", "--quiet"]
    camera_json = tmp_path / "camera.json"
    camera_json.write_text(json.dumps({"fx": 150.0, "fy": 151.0, "cx": 80.0, "cy": 60.0, "width": 160, "height": 120,
                                       "depth_scale": 1.0}))  # fmt: skip
    out = tmp_path / "given.yaml"
    assert main(["fit", str(stock), str(small_real_folder / "real"), "--camera", str(camera_json), "--out", str(out),
                 "--report", str(tmp_path / "given_report"), *args]) == 0  # fmt: skip
    written = load_preset(str(out))
    assert (written.focal_px, written.focal_y_px, written.cx_px, written.cy_px) == pytest.approx((150, 151, 80, 60))
    assert f"read from {camera_json}" in capsys.readouterr().out

    real = tmp_path / "real"
    shutil.copytree(small_real_folder / "real", real)
    for sequence in ("seq1", "seq2"):
        images = {str(i): {"cam_K": [148.0, 0, 79.0, 0, 149.0, 59.0, 0, 0, 1], "depth_scale": 1.0} for i in range(3)}
        (real / sequence / "scene_camera.json").write_text(json.dumps(images))
    out = tmp_path / "found.yaml"
    assert main(["fit", str(stock), str(real), "--out", str(out), "--report", str(tmp_path / "found_report"),
                 *args]) == 0  # fmt: skip
    written = load_preset(str(out))
    assert (written.focal_px, written.focal_y_px, written.cx_px, written.cy_px) == pytest.approx((148, 149, 79, 59))
    assert "read from the folder's" in capsys.readouterr().out
    assert json.loads((tmp_path / "found_report" / "unpaired_report.json").read_text())["depth_scale_m"] == 0.001

    images["1"]["depth_scale"] = 0.1  # 0.1 mm per unit in one image of one sequence
    (real / "seq2" / "scene_camera.json").write_text(json.dumps(images))
    assert main(["fit", str(stock), str(real), "--out", str(tmp_path / "scales.yaml"), *args]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "seq2/scene_camera.json: 1.depth_scale" in error[0] and "--depth-scale" in error[0]
    images["1"]["depth_scale"] = 1.0

    images["1"]["cam_K"] = [200.0, 0, 79.0, 0, 149.0, 59.0, 0, 0, 1]
    (real / "seq2" / "scene_camera.json").write_text(json.dumps(images))
    out = tmp_path / "refused.yaml"
    assert main(["fit", str(stock), str(real), "--out", str(out), *args]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "seq2/scene_camera.json: 1.cam_K" in error[0] and "differs" in error[0]
    assert not out.exists()
