"""ddsgen preview and the IR PNGs: a contact sheet a person can read, IR images that are not black.

A tiny sensor (160 x 120 px, kinect_v1's field of view) renders 2 frames of a small scene list
through the CLI, with torch.compile off (DDSGEN_NO_COMPILE=1): a couple of seconds.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from ddsgen.cli import main
from ddsgen.io.ir_png import EXPOSURE_PERCENTILE, decode_ir, encode_ir, ir_white_counts, read_ir_counts
from ddsgen.io.manifest import read_manifest
from ddsgen.io.png import read_depth_png, read_png8, read_png16
from ddsgen.preview import PANEL_KINDS, layout, write_preview
from tiny_inputs import tiny_preset_yaml, tiny_scenes_yaml, written_inputs

WIDTH, HEIGHT = 160, 120

@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """(preset path, scene list path), with torch.compile off in this process."""
    with written_inputs(tmp_path_factory.mktemp("inputs"), tiny_preset_yaml(WIDTH, HEIGHT, "tiny_preview"),
                        tiny_scenes_yaml(frames=2, clutter=(1, 2))) as paths:  # fmt: skip
        yield paths


@pytest.fixture(scope="module")
def rendered(inputs, tmp_path_factory):
    """A 2-frame render through the CLI, and the IR counts the sensor produced for each frame."""
    import ddsgen.io.framefiles as framefiles

    preset, scenes = inputs
    out = tmp_path_factory.mktemp("render") / "out"
    counts = {}
    original = framefiles.write_ir_png

    def keep_counts(path, image, full_scale):
        counts[Path(path).name] = np.array(image, dtype=np.float64)
        return original(path, image, full_scale)

    framefiles.write_ir_png = keep_counts  # the frame writer the runner calls (in this process: --workers 1)
    try:
        code = main(["render", preset, "--scenes", scenes, "-n", "2", "--out", str(out), "--seed", "3", "--quiet"])
    finally:
        framefiles.write_ir_png = original
    assert code == 0
    return out, counts


def sheet_pixel(panel, u: float, v: float) -> tuple[int, int]:
    """Sheet (x, y) of frame pixel (u, v) inside ``panel`` (panels show the frame scaled to their box)."""
    x = panel.x0 + (u + 0.5) * (panel.x1 - panel.x0) / WIDTH
    y = panel.y0 + (v + 0.5) * (panel.y1 - panel.y0) / HEIGHT
    return int(x), int(y)


def test_render_writes_a_contact_sheet_a_person_can_read(rendered):
    out, _ = rendered
    sheet_path = out / "preview.png"
    assert sheet_path.is_file()
    sheet = cv2.cvtColor(cv2.imread(str(sheet_path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB).astype(int)
    (width, height), boxes, _ = layout(2, WIDTH, HEIGHT)
    assert sheet.shape[:2] == (height, width)

    panels = write_preview(out, out / "again.png")[1]
    assert [(p.kind, p.frame) for p in panels] == [(k, f) for f in (0, 1) for k in PANEL_KINDS]
    assert [(p.x0, p.y0, p.x1, p.y1) for p in panels] == [b for row in boxes for b in row]
    assert (out / "again.png").read_bytes() == sheet_path.read_bytes()  # same folder, same bytes

    for record, row in zip(read_manifest(out / "manifest.jsonl"), (panels[:3], panels[3:])):
        depth_panel, ir_panel, mask_panel = row
        depth = read_depth_png(out / record["depth"], record["depth_scale"])
        # invalid depth is black (away from the border of the holes: the sheet is resampled)
        holes = cv2.erode((depth == 0).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        assert holes.sum() > 20, "the scene should have shadow holes"
        for v, u in zip(*np.nonzero(holes)):
            x, y = sheet_pixel(depth_panel, u, v)
            assert sheet[y, x].max() <= 8, (u, v, sheet[y, x])
        # valid depth is coloured, never black
        solid = cv2.erode((depth > 0).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        points = (sheet_pixel(depth_panel, u, v) for v, u in zip(*np.nonzero(solid)))
        colours = np.array([sheet[y, x] for x, y in points])
        assert colours.max(1).min() > 40
        # nearer is a different colour than farther: the colour map carries depth
        near, far = np.quantile(depth[solid], [0.1, 0.9])
        assert far - near > 0.1
        # the IR panel is auto-exposed: far from the old median of 2-6 / 255
        ir_pixels = sheet[ir_panel.y0 : ir_panel.y1, ir_panel.x0 : ir_panel.x1, 0]
        assert np.median(ir_pixels) > 40
        # instances: background black, each labelled object coloured inside its box
        mask = read_png16(out / record["mask"])
        for obj in record["objects"]:
            inside = cv2.erode((mask == obj["id"]).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
            if inside.sum() < 4:
                continue
            v, u = (int(np.median(a)) for a in np.nonzero(inside))
            if inside[v, u]:
                x, y = sheet_pixel(mask_panel, u, v)
                assert sheet[y, x].max() > 60


def quantisation_step(values: np.ndarray, white: float) -> np.ndarray:
    """Counts between PNG value v and v + 1 of the square-root encoding."""
    v = values.astype(np.float64)
    return white * ((v + 1.0) ** 2 - v**2) / 255.0**2


def test_ir_png_is_readable_and_round_trips_to_counts(rendered):
    out, counts = rendered
    for record in read_manifest(out / "manifest.jsonl"):
        white, gamma = record["ir_white_counts"], record["ir_gamma"]
        png = read_png8(out / record["ir"])
        true = counts[Path(record["ir"]).name]
        old_median = np.median(np.round(true / 1023.0 * 255.0))  # what the linear 10-bit -> 8-bit PNG showed
        assert old_median <= 8, "the test scene should be as dark as the issue's IR PNGs"
        assert np.median(png) > 40, f"IR PNG median {np.median(png)} of 255 still looks dark"
        recovered = read_ir_counts(out / record["ir"], white, gamma)
        unsaturated = png < 255
        # within one quantisation step where not saturated; saturated pixels are at least the top level
        error = np.abs(recovered[unsaturated] - true[unsaturated])
        assert (error <= quantisation_step(png[unsaturated], white) + 1e-3).all()
        assert (true[~unsaturated] >= decode_ir(np.array([254]), white)[0]).all()
        assert (~unsaturated).mean() <= 1.0 - EXPOSURE_PERCENTILE / 100.0 + 0.005


def test_ir_encoding_exposes_each_frame_on_its_own_percentile():
    rng = np.random.default_rng(0)
    counts = np.round(rng.gamma(4.54, 0.196, (120, 160)) * 25.0)  # speckled dim IR, ~20 counts of 1023
    white = ir_white_counts(counts, 1023.0)
    assert white == pytest.approx(np.percentile(counts, EXPOSURE_PERCENTILE), rel=1e-5)
    encoded = encode_ir(counts, white)
    assert encoded.max() == 255 and np.median(encoded) > 100
    # one count is resolved at the dim end (finer than the detector), exactly zero stays zero
    assert encode_ir(np.array([0.0, 1.0]), white).tolist()[0] == 0
    assert decode_ir(encode_ir(np.array([1.0]), white), white)[0] == pytest.approx(1.0, abs=0.2)
    assert ir_white_counts(np.zeros((4, 4)), 1023.0) == 1023.0  # black frame: the detector's range
    assert ir_white_counts(np.full((4, 4), 5000.0), 1023.0) == 1023.0


def test_render_no_preview_writes_none_and_resume_redraws_the_same_sheet(inputs, rendered, tmp_path):
    preset, scenes = inputs
    out = tmp_path / "out"
    assert main(["render", preset, "--scenes", scenes, "-n", "2", "--out", str(out), "--seed", "3", "--quiet",
                 "--no-preview"]) == 0  # fmt: skip
    assert not (out / "preview.png").exists()
    # the frames are the same bytes as the render with a preview: the sheet is not part of the frames
    reference = rendered[0]
    for record in read_manifest(out / "manifest.jsonl"):
        for key in ("depth", "ir", "mask"):
            assert (out / record[key]).read_bytes() == (reference / record[key]).read_bytes()
    assert (out / "manifest.jsonl").read_bytes() == (reference / "manifest.jsonl").read_bytes()
    # resuming the finished render (nothing to do) draws the sheet the uninterrupted render drew
    assert main(["render", preset, "--scenes", scenes, "-n", "2", "--out", str(out), "--seed", "3", "--quiet"]) == 0
    assert hashlib.sha256((out / "preview.png").read_bytes()).digest() == \
        hashlib.sha256((reference / "preview.png").read_bytes()).digest()  # fmt: skip


def test_preview_command_and_bad_input(rendered, tmp_path, capsys):
    out, _ = rendered
    sheet = tmp_path / "sheet.png"
    assert main(["preview", str(out), "--out", str(sheet), "--frames", "1"]) == 0
    image = cv2.imread(str(sheet))
    assert image.shape[:2] == layout(1, WIDTH, HEIGHT)[0][::-1]
    capsys.readouterr()
    for argv, words in (
        (["preview", str(tmp_path / "nothing")], "scan folder not found"),
        (["preview", str(tmp_path)], "not a scan folder"),
        (["preview", str(out), "--frames", "0"], "--frames"),
        (["preview", str(out), "--out", str(tmp_path / "sheet.jpg")], "PNG"),
    ):
        code = main(argv)
        err = capsys.readouterr().err
        assert code == 2 and len(err.strip().splitlines()) == 1 and words in err, (argv, err)
    assert not (tmp_path / "sheet.jpg").exists()


def test_manifest_rejects_a_bad_ir_encoding():
    from ddsgen.errors import InputError
    from ddsgen.io.manifest import validate_record

    record = {"frame": 0, "depth": "depth/000000.png", "depth_scale": 0.001, "objects": [], "seed": 0,
              "intrinsics": {"width": 4, "height": 3, "fx": 5.0, "fy": 5.0, "cx": 2.0, "cy": 1.5},
              "world_T_cam": np.eye(4).tolist()}  # fmt: skip
    validate_record(dict(record, ir_white_counts=566.0, ir_gamma=2.0))
    for key, value in (("ir_white_counts", 0.0), ("ir_white_counts", "bright"), ("ir_gamma", float("nan"))):
        with pytest.raises(InputError, match=key):
            validate_record(dict(record, **{key: value}))


def test_preview_of_a_bop_dataset_shows_its_masks_and_boxes(inputs, tmp_path):
    preset, scenes = inputs
    out = tmp_path / "bop"
    assert main(["render", preset, "--scenes", scenes, "-n", "1", "--out", str(out), "--format", "bop", "--quiet",
                 "--no-preview"]) == 0  # fmt: skip
    sheet_path, panels = write_preview(out, tmp_path / "bop.png")  # the BOP root: read as BOP, not as ddsgen
    sheet = cv2.cvtColor(cv2.imread(str(sheet_path)), cv2.COLOR_BGR2RGB).astype(int)
    depth_panel, ir_panel, mask_panel = panels
    ir = sheet[ir_panel.y0 : ir_panel.y1, ir_panel.x0 : ir_panel.x1]
    assert (ir == ir[2, 2]).all(-1).mean() > 0.95 and ir[2, 2].min() > 150, "BOP has no IR: a flat grey panel"
    masks = sorted((next(out.glob("train_pbr/*")) / "mask_visib").glob("000000_*.png"))
    visible = [read_png8(m) > 0 for m in masks]
    assert any(v.sum() > 20 for v in visible)
    for v in visible:
        inside = cv2.erode(v.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        if inside.sum() > 4:
            r, c = (int(np.median(a)) for a in np.nonzero(inside))
            if inside[r, c]:
                x, y = sheet_pixel(mask_panel, c, r)
                assert sheet[y, x].max() > 60


def test_preview_writes_into_ddsgen_renders_only(inputs, rendered, tmp_path, monkeypatch, capsys):
    """Without --out the sheet goes into a folder `ddsgen render` wrote (either layout); a dataset ddsgen did not
    make (here: the BOP render without ddsgen's scans folder, as a downloaded BOP dataset is) is left untouched and
    the sheet goes to the current folder."""
    import shutil

    from ddsgen.io.bop_writer import scans_folder
    from ddsgen.preview import default_sheet_path

    preset, scenes = inputs
    bop = tmp_path / "bop"
    assert main(["render", preset, "--scenes", scenes, "-n", "1", "--out", str(bop), "--format", "bop", "--quiet",
                 "--no-preview"]) == 0  # fmt: skip
    out = rendered[0]
    assert default_sheet_path(out) == out / "preview.png"
    assert default_sheet_path(bop) == bop / "preview.png"
    downloaded = tmp_path / "downloaded_bop"
    shutil.copytree(bop, downloaded)
    shutil.rmtree(scans_folder(downloaded))
    before = sorted(p.relative_to(downloaded) for p in downloaded.rglob("*"))
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    capsys.readouterr()
    assert main(["preview", str(downloaded)]) == 0
    assert sorted(p.relative_to(downloaded) for p in downloaded.rglob("*")) == before
    assert [p.name for p in work.iterdir()] == ["preview_downloaded_bop.png"]
    assert "preview_downloaded_bop.png" in capsys.readouterr().out


REAL_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.mark.skipif(not (REAL_DATA / "linemod_bop").is_dir(), reason="real data folder ../shared/data absent")
def test_preview_of_real_linemod_boxes_the_posed_object(tmp_path):
    from ddsgen.io.scanfolder import read_scan_folder
    from ddsgen.preview import load_rows

    title, rows = load_rows(REAL_DATA / "linemod_bop", frames=4)
    scan = read_scan_folder(REAL_DATA / "linemod_bop")[0]
    assert len(rows) == 1 and rows[0].ir is None and rows[0].instances is None and "linemod_bop" in title
    (obj_id, name, x, y, w, h), = rows[0].boxes
    obj = scan.objects[0]
    assert (obj_id, name) == (obj.id, obj.class_name)
    t = obj.cam_T_obj[:3, 3]  # the object's origin projects inside its box; a cat at ~1 m spans 60-200 px
    u, v = scan.intrinsics.fx * t[0] / t[2] + scan.intrinsics.cx, scan.intrinsics.fy * t[1] / t[2] + scan.intrinsics.cy
    assert x <= u <= x + w and y <= v <= y + h
    assert 40 <= w <= 250 and 40 <= h <= 250
    # the box holds the object: real depth inside it is near the pose's depth
    inside = rows[0].depth[y : y + h, x : x + w]
    assert abs(np.median(inside[inside > 0]) - t[2]) < 0.15
    path, panels = write_preview(REAL_DATA / "linemod_bop", tmp_path / "linemod.png")
    assert path.is_file() and [p.kind for p in panels] == list(PANEL_KINDS)
