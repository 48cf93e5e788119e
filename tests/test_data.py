"""ddsgen.data: the tensors equal what the files hold, frames rendered on the fly equal the rendered files, BOP
folders read the same labels, and the collate function pads varying object counts."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from ddsgen.data import RenderedFrames, ScanFolderDataset, collate_frames
from ddsgen.errors import InputError
from ddsgen.io.exr import read_exr
from ddsgen.io.ir_png import read_ir_counts
from ddsgen.io.manifest import read_manifest
from ddsgen.io.png import read_depth_png, read_png16
from ddsgen.runner import render_dataset

from tiny_inputs import tiny_preset_yaml, tiny_scenes_yaml, written_inputs

N, SEED = 3, 7


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    folder = tmp_path_factory.mktemp("data")
    with written_inputs(folder, tiny_preset_yaml(64, 48), tiny_scenes_yaml(frames=2, clutter=(1, 3))) as paths:
        render_dataset(*paths, N, str(folder / "out"), seed=SEED, progress=False)
        render_dataset(*paths, N, str(folder / "bop"), seed=SEED, progress=False, output_format="bop")
        yield folder, paths


def test_folder_tensors_are_the_files(rendered):
    folder, _ = rendered
    out = folder / "out"
    records = read_manifest(out / "manifest.jsonl")
    dataset = ScanFolderDataset(out)
    assert len(dataset) == N
    for record, item in zip(records, dataset):
        assert torch.equal(item["depth"], torch.from_numpy(read_exr(out / record["depth_exr"])))
        png = read_depth_png(out / record["depth"], record["depth_scale"])
        assert np.abs(item["depth"].numpy() - png).max() <= 0.0005 + 1e-6  # the PNG is the same depth in mm
        assert torch.equal(item["valid"], item["depth"] > 0) and item["valid"].any() and not item["valid"].all()
        assert torch.equal(item["clean"], torch.from_numpy(read_exr(out / record["clean"])))
        ir = read_ir_counts(out / record["ir"], record["ir_white_counts"], record["ir_gamma"])
        assert torch.equal(item["ir"], torch.from_numpy(ir))
        assert torch.equal(item["instance"], torch.from_numpy(read_png16(out / record["mask"]).astype(np.int64)))
        objects = record["objects"]
        assert item["instance_ids"].tolist() == [o["id"] for o in objects]
        assert item["obj_ids"].tolist() == [o["obj_id"] for o in objects] and min(item["obj_ids"].tolist()) >= 1
        names = {row["id"]: row["class"] for row in dataset.classes}
        assert [names[i] for i in item["obj_ids"].tolist()] == [o["class"] for o in objects]
        assert item["boxes"].tolist() == [o["bbox"] for o in objects]
        for k, obj in enumerate(objects):
            pose = np.asarray(obj["cam_T_obj"])
            assert np.allclose(item["rotations"][k].numpy(), pose[:3, :3], atol=1e-7)
            assert np.allclose(item["translations"][k].numpy(), pose[:3, 3], atol=1e-7)
        intr = record["intrinsics"]
        K = [[intr["fx"], 0, intr["cx"]], [0, intr["fy"], intr["cy"]], [0, 0, 1]]
        assert torch.equal(item["intrinsics"], torch.tensor(K, dtype=torch.float32))
        assert int(item["frame"]) == record["frame"]


def test_frames_rendered_on_the_fly_equal_the_rendered_files(rendered):
    folder, (preset, scenes) = rendered
    on_disk = ScanFolderDataset(folder / "out")
    online = RenderedFrames(preset, N, scenes, seed=SEED)
    loader = DataLoader(online, batch_size=None, num_workers=2)  # frames interleave: 0 (worker 0), 1 (1), 2 (0)
    got = list(loader)
    assert [int(item["frame"]) for item in got] == list(range(N))
    for item, expected in zip(got, on_disk):
        assert item.keys() == expected.keys()
        for key in expected:
            assert torch.equal(item[key], expected[key]), key


def test_the_bop_export_reads_the_same_labels(rendered):
    folder, _ = rendered
    own = ScanFolderDataset(folder / "bop" / "ddsgen")
    bop = ScanFolderDataset(folder / "bop")
    assert len(bop) == len(own) == N
    for a, b in zip(bop, own):
        keep = b["visible_fraction"] > 0  # BOP's reader leaves out objects with nothing visible
        assert torch.equal(a["instance"], b["instance"])  # rebuilt from mask_visib/
        assert a["obj_ids"].tolist() == b["obj_ids"][keep].tolist()
        assert a["boxes"].tolist() == b["boxes"][keep].tolist()
        assert torch.allclose(a["translations"], b["translations"][keep], atol=1e-6)  # mm in the JSON
        assert torch.equal(a["valid"], b["valid"]) and "ir" not in a and "clean" not in a


def test_collate_pads_varying_object_counts(rendered):
    folder, _ = rendered
    dataset = ScanFolderDataset(folder / "out")
    items = [dataset[i] for i in range(N)]
    counts = [len(i["instance_ids"]) for i in items]
    assert len(set(counts)) > 1  # frames 0-1 share a layout, frame 2 has another: the counts differ
    batch = collate_frames(items)
    most = max(counts)
    assert batch["depth"].shape == (N, 48, 64) and batch["intrinsics"].shape == (N, 3, 3)
    assert batch["object_valid"].sum(dim=1).tolist() == counts
    assert batch["boxes"].shape == (N, most, 4) and batch["rotations"].shape == (N, most, 3, 3)
    for row, item in enumerate(items):
        n = counts[row]
        assert torch.equal(batch["obj_ids"][row, :n], item["obj_ids"])
        assert (batch["obj_ids"][row, n:] == 0).all() and (batch["boxes"][row, n:] == 0).all()
        assert torch.equal(batch["rotations"][row, n:], torch.eye(3).expand(most - n, 3, 3))


def test_bad_inputs_fail_before_any_worker_starts(rendered, tmp_path):
    folder, (preset, scenes) = rendered
    with pytest.raises(InputError, match="--camera: expected four numbers"):
        RenderedFrames(preset, 2, scenes, camera="1,2")
    with pytest.raises(InputError, match="scan folder not found"):
        ScanFolderDataset(tmp_path / "absent")
