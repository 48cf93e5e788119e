"""The loss terms' fast forms against their plain definitions (ddsgen.realscan.losses).

The fit and the diagnosis evaluate :func:`frame_loss` hundreds of times per run, so its terms are computed
without boolean indexing and with the real side memoised; these tests hold them to the textbook formulas.
"""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from ddsgen.realscan import losses
from ddsgen.realscan.losses import CLIP_MM, LossWeights, binned_roughness_gap, frame_loss, without_plane_pose


def _plane_frame(seed: int, height: int = 48, width: int = 64):
    """A frame whose support plane (instance 0) surrounds an object (instance 1), real depth 0.6-2.4 m, with
    a random mask of pixels valid in both and an error that is affine in disparity plus noise and outliers."""
    g = torch.Generator().manual_seed(seed)
    instance = torch.zeros(height, width, dtype=torch.int32)
    instance[12:30, 20:40] = 1
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32),
                          indexing="ij")  # fmt: skip
    real = 0.6 + 1.8 * v / height + 0.1 * torch.rand(height, width, generator=g)
    both = torch.rand(height, width, generator=g) > 0.25
    real = torch.where(both | (torch.rand(height, width, generator=g) > 0.5), real, torch.zeros_like(real))
    both &= real > 0
    err = (0.4 + 0.02 * u - 0.01 * v) * real**2 + torch.randn(height, width, generator=g)
    err[5, 5] = 300.0  # beyond the clip
    err = torch.where(both, err, torch.zeros_like(err))
    return SimpleNamespace(instance=instance, real_depth=real), both, err


def _reference_without_plane_pose(err: torch.Tensor, frame, both: torch.Tensor) -> torch.Tensor:
    """The definition: on the plane's pixels (boolean-indexed), err / z^2 minus its least-squares fit a + b u + c v
    (u, v in units of the image's width and height), times z^2; float64 throughout."""
    plane = both & (frame.instance == 0)
    height, width = err.shape
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64) / height,
                          torch.arange(width, dtype=torch.float64) / width, indexing="ij")  # fmt: skip
    z2 = frame.real_depth.double()[plane] ** 2
    r = err.double().clamp(-CLIP_MM, CLIP_MM)[plane] / z2
    basis = torch.stack([torch.ones_like(r), u[plane], v[plane]], dim=1)
    coef = torch.linalg.lstsq(basis, r[:, None]).solution[:, 0]
    explained = torch.zeros(height, width, dtype=torch.float64)
    explained[plane] = (basis @ coef) * z2
    return err.double() - explained


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_plane_pose_removal_is_the_least_squares_fit_and_so_is_its_gradient(seed):
    frame, both, err = _plane_frame(seed)
    err = err.requires_grad_(True)
    fast = without_plane_pose(err, frame, both)
    reference = _reference_without_plane_pose(err, frame, both)
    assert fast.dtype == err.dtype and fast.shape == err.shape
    assert torch.allclose(fast.double(), reference, atol=1e-4, rtol=1e-5)
    # The residual is orthogonal to the basis on the plane (what least squares means), and the object keeps its error.
    plane = both & (frame.instance == 0)
    objects = both & (frame.instance == 1)
    assert torch.equal(fast[objects].detach(), err[objects].detach())
    assert float((fast - err).detach()[plane].abs().max()) > 0.05  # something was removed
    # Gradients of a weighted sum (a loss) agree with the reference's.
    weights = torch.rand(err.shape, generator=torch.Generator().manual_seed(seed + 10))
    (g_fast,) = torch.autograd.grad((fast * weights).sum(), err)
    (g_ref,) = torch.autograd.grad((reference * weights.double()).sum(), err)
    assert torch.isfinite(g_fast).all()
    assert torch.allclose(g_fast, g_ref.float(), atol=1e-4, rtol=1e-4)


def test_binned_roughness_gap_is_the_pixel_weighted_mean_of_per_bin_hubers():
    g = torch.Generator().manual_seed(3)
    height, width = 40, 50
    z = 0.5 + 2.0 * torch.rand(height, width, generator=g)
    z[:3] = 0.0  # no hit
    ok = (torch.rand(height, width, generator=g) > 0.3) & (z > 0)
    r_sim = 4.0 * torch.rand(height, width, generator=g)
    r_real = 4.0 * torch.rand(height, width, generator=g) + torch.where(z > 1.5, 8.0, 0.0)
    zero = torch.zeros(())
    got = float(binned_roughness_gap(r_sim, r_real, z, ok, zero))
    # The definition, in numpy: bins of 0.25 m of the pixels of ok, those of >= 20 px, weighted by their count.
    bins = np.floor(z.numpy()[ok.numpy()] / losses.ROUGHNESS_BIN_M).astype(int)
    total, weight = 0.0, 0
    for b in np.unique(bins):
        members = bins == b
        n = int(members.sum())
        if n < 20:
            continue
        gap = r_sim.numpy()[ok.numpy()][members].mean() - r_real.numpy()[ok.numpy()][members].mean()
        total += n * float(losses.huber(torch.tensor(gap, dtype=torch.float64)))
        weight += n
    assert weight > 0 and total > 0
    assert got == pytest.approx(total / weight, rel=1e-5)
    assert float(binned_roughness_gap(r_sim, r_real, z, torch.zeros_like(ok), zero)) == 0.0


def _validity_frame(height: int = 30, width: int = 40):
    g = torch.Generator().manual_seed(5)
    region = torch.ones(height, width, dtype=torch.bool)
    region[:, :6] = False
    real_valid = torch.rand(height, width, generator=g) > 0.2
    depth = torch.full((height, width), 1.2)
    frame = SimpleNamespace(region=region, real_depth=torch.where(real_valid, depth, torch.zeros_like(depth)),
                            real_valid=real_valid, clean_depth=depth, plane=None,
                            instance=torch.zeros(height, width, dtype=torch.int32),
                            intrinsics=SimpleNamespace(fx=100.0), resolved_depth_m=float("inf"))  # fmt: skip
    soft = torch.rand(height, width, generator=g)
    sim = SimpleNamespace(depth=depth, valid=soft > 0.5, valid_soft=soft)
    return frame, sim


def _reference_validity(frame, sim) -> float:
    """VALIDITY_MM x the region's mean squared difference of the local (k x k, masked) valid rates."""
    k = losses.local_window(frame.intrinsics.fx)
    ls, _ = losses.masked_local_mean(sim.valid_soft.float(), frame.region, k)
    lr, _ = losses.masked_local_mean(frame.real_valid.float(), frame.region, k)
    return float(losses.VALIDITY_MM * ((ls - lr) ** 2)[frame.region].mean())


def test_validity_term_with_the_memoised_real_side_follows_the_real_mask():
    frame, sim = _validity_frame()
    first = float(frame_loss(sim, frame, LossWeights())["validity"])
    assert first == pytest.approx(_reference_validity(frame, sim), rel=1e-5)
    assert float(frame_loss(sim, frame, LossWeights())["validity"]) == first  # from the memo: the same number
    # An in-place change of the real mask, or another region, is seen.
    frame.real_valid[10:20, 10:30] = False
    changed = float(frame_loss(sim, frame, LossWeights())["validity"])
    assert changed != pytest.approx(first, rel=1e-3)
    assert changed == pytest.approx(_reference_validity(frame, sim), rel=1e-5)
    frame.region = frame.region.clone()
    frame.region[:, 30:] = False
    assert float(frame_loss(sim, frame, LossWeights())["validity"]) == pytest.approx(_reference_validity(frame, sim),
                                                                                     rel=1e-5)  # fmt: skip


def test_tensor_memo_follows_its_tensors_and_stays_bounded():
    """The memo behind the speckle field and the real validity side: one computation per tensor state; a new tensor
    or an in-place change computes anew; a full memo evicts its oldest entry only when a key is added."""
    from ddsgen.tensor_memo import memoised

    memo, calls = {}, []
    a, b = torch.zeros(3), torch.ones(3)

    def compute(x):
        calls.append(float(x.sum()))
        return x.sum().item()

    assert memoised(memo, (a,), ("k",), 2, lambda: compute(a)) == 0.0
    assert memoised(memo, (a,), ("k",), 2, lambda: compute(a)) == 0.0 and len(calls) == 1  # served
    assert memoised(memo, (a,), ("other",), 2, lambda: compute(a)) == 0.0 and len(calls) == 2  # another key
    a += 2.0  # in place: its version counter moves
    assert memoised(memo, (a,), ("k",), 2, lambda: compute(a)) == 6.0 and len(calls) == 3
    assert len(memo) == 2  # the oldest went to make room
    assert memoised(memo, (b,), ("k",), 2, lambda: compute(b)) == 3.0 and len(memo) == 2


def test_resolved_depth_is_where_one_disparity_quantum_is_the_clip():
    """Kinect V1 (f b = 572.41 px x 0.075 m): 1/8 px steps resolve to 4.14 m, 1/4 px to 2.93 m; there one step
    of the quantum is a CLIP_MM depth step (z^2 step / (f b))."""
    fb = 572.41 * 0.075
    for step, expected in ((1 / 8, 4.14), (1 / 4, 2.93)):
        z = losses.resolved_depth_m(fb, step)
        assert z == pytest.approx(expected, abs=0.005)
        assert 1000.0 * z**2 * step / fb == pytest.approx(CLIP_MM)


def test_surfaces_beyond_the_resolved_depth_count_in_the_depth_term_only_where_resolved():
    """A wall at 6 m (beyond 4.14 m) beside one at 2 m: a 40 mm error on the far wall moves neither the depth nor
    the per-pixel term; the same error on the near wall moves the depth term; the far wall's holes still count in
    the validity term, and its noise texture in the gradient term."""
    height, width = 40, 60
    clean = torch.full((height, width), 2.0)
    clean[:, 30:] = 6.0
    g = torch.Generator().manual_seed(3)
    real = clean + 0.01 * torch.randn(height, width, generator=g)
    all_valid = torch.ones(height, width, dtype=torch.bool)
    frame = SimpleNamespace(region=all_valid.clone(), real_depth=real, real_valid=all_valid.clone(), clean_depth=clean,
                            plane=None, instance=torch.zeros(height, width, dtype=torch.int32),
                            intrinsics=SimpleNamespace(fx=572.41),
                            resolved_depth_m=losses.resolved_depth_m(572.41 * 0.075, 1 / 8))  # fmt: skip
    far = clean > 5.0

    def terms(error_m, valid=all_valid):
        sim = SimpleNamespace(depth=real + error_m, valid=valid, valid_soft=valid.float())
        return {k: float(v) for k, v in frame_loss(sim, frame, LossWeights()).items()}

    def on(mask, value):
        return torch.where(mask, value, torch.zeros_like(real))

    exact = terms(torch.zeros_like(real))
    assert exact["depth"] == 0.0 and exact["validity"] == 0.0 and exact["gradient"] == 0.0
    far_error = terms(on(far, torch.full_like(real, 0.04)))
    assert far_error["depth"] == 0.0 and far_error["pixel"] == 0.0
    assert terms(on(~far, torch.full_like(real, 0.04)))["depth"] > 30.0
    assert terms(on(far, 0.1 * torch.randn(height, width, generator=g)))["gradient"] > 10.0  # rougher far wall
    far_hole = all_valid.clone()
    far_hole[10:30, 35:55] = False
    assert terms(torch.zeros_like(real), far_hole)["validity"] > 1.0
    frame.resolved_depth_m = float("inf")  # without the limit the far wall's error counts
    assert terms(on(far, torch.full_like(real, 0.04)))["depth"] > 15.0
