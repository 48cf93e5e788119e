"""Feature distance or patch discriminator? The measurement behind docs/validation.md.

Renders 8 frames each of: sensor S1 (the stock preset) on scene list A, S1 on scene list B,
sensor S2 (other SNR, beta, confidence threshold, n_sub) on A -- at WIDTH x 3/4 WIDTH. Then:

* feature distance (ddsgen.fit.unpaired.features): d(S1 A, S1 B) is the scene effect,
  d(S1 A, S2 A) the sensor effect;
* a small patch discriminator (2 conv layers, 32x32 patches of depth minus the patch median and
  validity, the paper's kind of input), trained with Adam to tell S1 A from S1 B (scene) and
  S1 A from S2 A (sensor); held-out accuracy on frames it never saw.

A statistic that separates scene lists as well as sensors would move the sensor's parameters
to imitate scene content. Prints ``bench: NAME VALUE``. Usage: python bench/unpaired_choice.py [WIDTH]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

sys.path.insert(0, str(ROOT / "bench"))
from unpaired_hidden_device import scene_list_a  # noqa: E402
from ddsgen.fit.unpaired.features import distance_terms, frame_features, pool  # noqa: E402
from ddsgen.realscan.realfolder import round_like  # noqa: E402
from ddsgen.fit.unpaired.search import camera_for, cast_scenes, render_depths  # noqa: E402
from ddsgen.preset import load_preset  # noqa: E402
from ddsgen.scene.scenelist import load_scene_list, scene_list_from_dict  # noqa: E402

PATCH = 32


def patches(depths: list[np.ndarray], rng: np.random.Generator, per_frame: int = 64) -> np.ndarray:
    """(N, 2, PATCH, PATCH): depth minus the patch's median valid depth (m), and validity."""
    out = []
    for depth in depths:
        h, w = depth.shape
        for _ in range(per_frame):
            y, x = rng.integers(0, h - PATCH), rng.integers(0, w - PATCH)
            p = depth[y:y + PATCH, x:x + PATCH]
            valid = p > 0
            centred = np.where(valid, p - (np.median(p[valid]) if valid.any() else 0.0), 0.0)
            out.append(np.stack([centred, valid.astype(np.float64)]))
    return np.asarray(out, np.float32)


def discriminator_accuracy(a: list[np.ndarray], b: list[np.ndarray], seed: int = 0) -> float:
    """Held-out accuracy of a small CNN separating patches of ``a`` from ``b`` (first 6 frames
    train, the rest test)."""
    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    train = np.concatenate([patches(a[:6], rng), patches(b[:6], rng)])
    test = np.concatenate([patches(a[6:], rng), patches(b[6:], rng)])
    y_train = np.r_[np.zeros(len(train) // 2), np.ones(len(train) // 2)].astype(np.float32)
    y_test = np.r_[np.zeros(len(test) // 2), np.ones(len(test) // 2)].astype(np.float32)
    net = torch.nn.Sequential(
        torch.nn.Conv2d(2, 16, 5, stride=2), torch.nn.LeakyReLU(0.2), torch.nn.Conv2d(16, 32, 5, stride=2),
        torch.nn.LeakyReLU(0.2), torch.nn.AdaptiveAvgPool2d(1), torch.nn.Flatten(), torch.nn.Linear(32, 1),
    )  # fmt: skip
    opt = torch.optim.Adam(net.parameters(), 1e-3)
    x, y = torch.from_numpy(train), torch.from_numpy(y_train)
    x[:, 0] *= 100.0  # centred depth in cm: unit scale for the first layer
    for _ in range(300):
        idx = torch.randint(0, len(x), (128,))
        loss = torch.nn.functional.binary_cross_entropy_with_logits(net(x[idx]).squeeze(1), y[idx])
        opt.zero_grad()
        loss.backward()
        opt.step()
    xt = torch.from_numpy(test)
    xt[:, 0] *= 100.0
    with torch.no_grad():
        predicted = (net(xt).squeeze(1) > 0).float().numpy()
    return float((predicted == y_test).mean())


def main(width: int = 320) -> None:
    torch.set_num_threads(1)
    s1 = camera_for(load_preset("kinect_v1"), width, width * 3 // 4)
    s2 = s1.replace(emitted_intensity=4e6, softargmax_beta=30.0, min_confidence=0.2, subpixel_level=3)
    a, b = scene_list_from_dict(scene_list_a()), load_scene_list(None)
    geo_a, geo_b = cast_scenes(s1, a, 8, 21), cast_scenes(s1, b, 8, 22)
    render = lambda preset, geo: [round_like(d, 0.001) for d in render_depths(preset, geo, 3)]  # noqa: E731
    s1a, s1b, s2a = render(s1, geo_a), render(s1, geo_b), render(s2, geo_a)
    fb = s1.focal_px * s1.baseline_m
    feats = {k: pool([frame_features(d, fb) for d in v]) for k, v in (("s1a", s1a), ("s1b", s1b), ("s2a", s2a))}
    scene = distance_terms(feats["s1b"], feats["s1a"])
    sensor = distance_terms(feats["s2a"], feats["s1a"])
    for name, terms in (("scene", scene), ("sensor", sensor)):
        print(f"bench: choice_feature_distance_{name} {terms['total']:.4f} "
              f"(noise {terms['noise']:.4f}, holes {terms['holes']:.4f})")
    print(f"bench: choice_discriminator_accuracy_scene {discriminator_accuracy(s1a, s1b):.3f}")
    print(f"bench: choice_discriminator_accuracy_sensor {discriminator_accuracy(s1a, s2a):.3f}")


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:]))
