"""The block matcher (ddsgen/sensor/matcher/): accuracy on known disparities, exact band
stitching, the C and torch paths agreeing (forward and backward; torch when there is no C
compiler), gradients against finite differences, finite gradients everywhere, memory bounded
by the band, and the reference-phase layout of docs/ARCHITECTURE.md.

The synthetic scenes use an analytic dot pattern (Gaussian dots, sigma 0.6 px, ~11 % of the
area lit, like a Kinect pattern), so the observed image I(u, v) = R(u - d(u, v), v) and the
reference phases R(j - pad - s/S, v) are exact samples of one continuous function: any error
is the matcher's, not interpolation's.
"""

from __future__ import annotations

import math
import weakref

import numpy as np
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten

from torch_threads import torch_threads
from ddsgen.sensor import matcher as M
from ddsgen.sensor.matcher import kernel, reference, torch_path
from ddsgen.sensor.matcher.kernel import SEARCH_LANES
from ddsgen.sensor.matcher import match, stereo_reference_phases

SIGMA = 0.6


def _dots(height, x_min, x_max, seed, density=0.11):
    """Random dot centres covering rows [-3, height + 3) and x in [x_min, x_max)."""
    rng = np.random.default_rng(seed)
    area = (height + 6) * (x_max - x_min)
    count = int(density * area / (2 * math.pi * SIGMA**2))
    xs = rng.uniform(x_min, x_max, count)
    ys = rng.uniform(-3, height + 3, count)
    amp = rng.uniform(0.6, 1.0, count)
    return xs, ys, amp


def _render(dots, x, y):
    """Sum of Gaussian dots at continuous positions x, y (same shape)."""
    xs, ys, amp = dots
    out = np.zeros(x.shape, dtype=np.float64)
    for row in range(x.shape[0]):
        near = np.abs(ys - y[row, 0]) < 4 * SIGMA
        dx = x[row][:, None] - xs[near][None, :]
        dy = y[row][:, None] - ys[near][None, :]
        out[row] = (amp[near] * np.exp(-(dx**2 + dy**2) / (2 * SIGMA**2))).sum(axis=1)
    return out


def _scene(height, width, disparity, n_sub=2, pad=None, noise=0.0, seed=0, dtype=torch.float32):
    """(observed, reference_phases, pad, true disparity) for a disparity map (H, W) or constant."""
    d = np.broadcast_to(np.asarray(disparity, dtype=np.float64), (height, width))
    pad = pad or int(math.ceil(d.max())) + 12
    dots = _dots(height, -pad - 3, width + 3, seed)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    observed = 40 + 800 * _render(dots, u - d, v)
    if noise:
        observed += np.random.default_rng(seed + 1).normal(0, noise, observed.shape)
    steps = 2**n_sub
    vj, j = np.mgrid[0:height, 0 : width + pad].astype(np.float64)
    phases = np.stack([_render(dots, j - pad - s / steps, vj) for s in range(steps)])
    return (torch.tensor(observed, dtype=dtype), torch.tensor(phases, dtype=dtype), pad, d.astype(np.float32))


@pytest.fixture(scope="module")
def sloped():
    """A plane tilted in both directions: d = 14 + 0.06 u + 0.03 v (px), mild sensor noise."""
    height, width = 40, 120
    v, u = np.mgrid[0:height, 0:width]
    return _scene(height, width, 14.0 + 0.06 * u + 0.03 * v, noise=4.0, seed=3)


def _interior(mask, block=9):
    h = block // 2
    out = np.zeros_like(mask)
    out[h:-h, h:-h] = mask[h:-h, h:-h]
    return out


# ---------------------------------------------------------------------------------------
# Accuracy
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("true_d", [17.0, 23.6])
@pytest.mark.parametrize("backend", ["c", "torch"])
def test_constant_disparity_recovered_within_subpixel_step(true_d, backend):
    if backend == "c" and M.integer_search_backend() != "c":
        pytest.skip("no C compiler: the C kernel is unavailable")
    observed, phases, pad, d = _scene(32, 96, true_d, n_sub=2, noise=2.0, seed=1)
    result = match(observed, phases, pad, 5, pad - 12, 9, 15.0, 2, 64, 0.05, backend=backend, compile=False)
    valid = result.valid.numpy()
    inner = _interior(np.ones_like(valid))
    assert valid[inner].mean() > 0.97, "textured pixels must be valid"
    error = np.abs(result.disparity.numpy() - d)[inner & valid]
    step = 0.25
    # Quantised output: the best possible error is half a step; allow the step itself (the
    # soft-argmax over K - 1/2 .. K + 1/2 is pulled towards the integer peak K by < 1/2 step).
    assert np.mean(error <= step + 1e-6) > 0.97, f"median error {np.median(error):.3f} px"
    assert np.median(error) < 0.2


def test_quarter_pixel_candidates_do_not_lock_the_eighth_pixel_output_to_their_grid():
    """At n_sub 3 the refinement's candidates are 1/4 px apart by default (M.REFINE_LEVEL, half the
    cost of 1/8 px ones): the soft-argmax stays continuous in the true shift, as accurate as with
    1/8-px candidates, while 1/2-px candidates lock to their grid (measured: worst mean error over
    the shifts 0.0048 px at 1/4 and at 1/8 px, 0.035 px at 1/2 px)."""
    worst = {}
    for level in (1, 2, 3):
        errors = []
        for k in range(0, 17, 2):
            true_d = 17.0 + k / 16
            observed, phases, pad, _ = _scene(20, 80, true_d, n_sub=3, seed=5)
            result = match(observed, phases, pad, 5, 24, 9, 15.0, 3, quantize=False,
                           refine_level=None if level == M.REFINE_LEVEL else level)  # fmt: skip
            inside = _interior(result.valid.numpy())
            errors.append(float((result.disparity.numpy()[inside] - true_d).mean()))
        worst[level] = max(abs(e) for e in errors)
    assert M.REFINE_LEVEL == 2
    assert worst[2] < 0.01 and worst[3] < 0.01, worst
    assert worst[2] < worst[3] + 0.002, worst
    assert worst[1] > 2 * worst[2], worst  # the test can tell a grid-locked estimator


def test_sloped_disparity_recovered_within_subpixel_step(sloped):
    observed, phases, pad, d = sloped
    result = match(observed, phases, pad, 8, 30, 9, 15.0, 2, 64, 0.05, compile=False)
    valid = result.valid.numpy()
    inner = _interior(np.ones_like(valid))
    assert valid[inner].mean() > 0.95
    error = np.abs(result.disparity.numpy() - d)[inner & valid]
    assert np.mean(error <= 0.25 + 1e-6) > 0.9, f"median error {np.median(error):.3f} px"
    assert np.percentile(error, 99) < 1.0


def test_output_is_quantised_to_the_subpixel_step(sloped):
    observed, phases, pad, _ = sloped
    result = match(observed, phases, pad, 8, 30, 9, 15.0, 2, 64, 0.05, compile=False)
    steps = result.disparity * 4
    assert torch.equal(steps, torch.round(steps))
    assert result.disparity.dtype == torch.float32
    assert result.confidence.min() >= 0 and result.confidence.max() <= 1


def test_backends_agree(sloped):
    if M.integer_search_backend() != "c":
        pytest.skip("no C compiler")
    observed, phases, pad, _ = sloped
    a = match(observed, phases, pad, 8, 30, 9, 15.0, 2, 64, 0.05, backend="c", compile=False, quantize=False)
    b = match(observed, phases, pad, 8, 30, 9, 15.0, 2, 64, 0.05, backend="torch", compile=False, quantize=False)
    close = (a.disparity - b.disparity).abs() < 1e-3
    assert close.float().mean() > 0.995  # differences only at exact ties of the integer search
    assert (a.confidence - b.confidence).abs().max() < 1e-3  # float32 running sums vs explicit sums
    # With the confirmed-match rule: the same validity, and both peaks' integer disparities (the second
    # one is searched where the rule may use it: a peak above its threshold at a non-unique match).
    a, b = (match(observed, phases, pad, 8, 30, 9, 15.0, 2, 64, 0.05, backend=backend, compile=False, quantize=False,
                  confirmed_match_zncc=0.0) for backend in ("c", "torch"))  # fmt: skip
    assert (a.second_peak_px >= 0).sum() > 0
    assert (a.peak_px == b.peak_px).float().mean() > 0.995
    assert (a.second_peak_px == b.second_peak_px).float().mean() > 0.995
    assert (a.valid == b.valid).float().mean() > 0.995


def test_c_and_torch_paths_give_the_same_depth_and_gradients_in_float32(small64):
    """The C kernels (float32 CPU) and the torch twin on the same float32 IR pair: the same
    disparity, hence depth, to float32 rounding, and the same gradients w.r.t. the observed
    image and beta (both paths' backward, not just the forward)."""
    if M.integer_search_backend() != "c":
        pytest.skip("no C compiler")
    observed, phases, pad = (x.float() if torch.is_tensor(x) else x for x in small64)
    weights = torch.randn(observed.shape, generator=torch.Generator().manual_seed(1))

    def run(backend):
        obs = observed.clone().requires_grad_(True)
        beta = torch.tensor(15.0, requires_grad=True)
        result = match(obs, phases, pad, 4, 16, 5, beta, 2, 5, 0.05, quantize=False, backend=backend, compile=False)
        (result.disparity * weights).sum().backward()
        return result, obs.grad, beta.grad

    (c, c_grad, c_beta), (t, t_grad, t_beta) = run("c"), run("torch")
    both = (c.valid & t.valid).numpy()
    assert both.mean() > 0.8
    focal_baseline = 572.41 * 0.075  # kinect_v1: depth = f b / d
    depth_c, depth_t = focal_baseline / c.disparity.detach().numpy(), focal_baseline / t.disparity.detach().numpy()
    assert np.abs(depth_c - depth_t)[both].max() < 1e-5 * depth_t[both].max()
    assert torch.equal(c.valid, t.valid)
    assert (c_grad - t_grad).norm() < 1e-3 * t_grad.norm()
    assert abs(float(c_beta - t_beta)) < 1e-3 * abs(float(t_beta)) + 1e-6


def test_without_a_c_compiler_the_torch_path_gives_the_same_disparity(sloped, tmp_path, monkeypatch, caplog):
    """No compiler on the machine (``$CC`` names none): one warning, no file in the cache, the
    torch path runs and agrees with the C path (where that exists)."""
    observed, phases, pad, _ = sloped
    args = (observed, phases, pad, 8, 30, 9, 15.0, 2, 64, 0.05)
    with_c = match(*args, compile=False, quantize=False) if M.integer_search_backend() == "c" else None
    monkeypatch.setattr(kernel, "_KERNEL", None)
    monkeypatch.setattr(kernel, "_KERNEL_TRIED", False)
    monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    monkeypatch.setenv("DDSGEN_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("DDSGEN_NO_C_KERNEL", raising=False)
    with caplog.at_level("WARNING"):
        assert M.integer_search_backend() == "torch"
    assert "C kernel unavailable" in caplog.text
    assert not list((tmp_path / "cache").rglob("*.so")) and not list((tmp_path / "cache").rglob("*.c"))
    with pytest.raises(RuntimeError, match="unavailable"):
        match(*args, backend="c")
    without_c = match(*args, compile=False, quantize=False)
    inner = _interior(np.ones(observed.shape, dtype=bool))
    assert without_c.valid.numpy()[inner].mean() > 0.95
    if with_c is not None:
        close = (with_c.disparity - without_c.disparity).abs() < 1e-3
        assert close.float().mean() > 0.995  # differences only at exact ties of the integer search


# ---------------------------------------------------------------------------------------
# Bands
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("backend", ["c", "torch"])
def test_band_split_is_identical_to_one_band(sloped, backend):
    if backend == "c" and M.integer_search_backend() != "c":
        pytest.skip("no C compiler")
    observed, phases, pad, _ = sloped
    observed = observed.clone().requires_grad_(True)

    def run(rows):
        observed.grad = None
        result = match(observed, phases, pad, 8, 30, 9, 15.0, 2, rows, 0.05, backend=backend, compile=False)
        (result.disparity * torch.linspace(0, 1, observed.shape[1])).sum().backward()
        return result, observed.grad.clone()

    whole, grad_whole = run(1000)
    for rows in (1, 7, 16):
        split, grad_split = run(rows)
        assert torch.equal(split.disparity, whole.disparity), f"band_rows={rows}"
        assert torch.equal(split.confidence, whole.confidence)
        assert torch.equal(split.valid, whole.valid)
        assert torch.allclose(grad_split, grad_whole, rtol=1e-5, atol=1e-7)


def test_c_refinement_does_not_depend_on_the_thread_count(sloped):
    """Render workers run 1 thread, tests and fits more: per-pixel values and gradients
    (including the beta reduction) must be bit-identical."""
    if M.integer_search_backend() != "c":
        pytest.skip("no C compiler")
    observed, phases, pad, _ = sloped
    out = []
    for threads in (1, 2):
        with torch_threads(threads):
            obs = observed.clone().requires_grad_(True)
            beta = torch.tensor(15.0, requires_grad=True)
            result = match(obs, phases, pad, 8, 30, 9, beta, 2, 16, 0.05, quantize=False)
            (result.disparity * torch.linspace(0, 1, obs.shape[1])).sum().backward()
            out.append((result.disparity.detach(), obs.grad, beta.grad))
    for a, b in zip(*out):
        assert torch.equal(a, b)


def test_no_grad_c_path_never_calls_torch_compile(sloped, monkeypatch):
    """The render path (no gradient) must not pay torch.compile's first-call cost."""
    if M.integer_search_backend() != "c":
        pytest.skip("no C compiler")

    def refuse(*args, **kwargs):
        raise AssertionError("torch.compile called")

    monkeypatch.setattr(torch, "compile", refuse)
    monkeypatch.setattr(torch_path, "_COMPILED", {})
    observed, phases, pad, _ = sloped
    with torch.no_grad():
        result = match(observed, phases, pad, 8, 30, 9, 15.0, 2, 64, 0.05)
    assert result.valid.float().mean() > 0.5
    obs = observed.clone().requires_grad_(True)  # the C gradient path does not compile either
    match(obs, phases, pad, 8, 30, 9, 15.0, 2, 64, 0.05).disparity.sum().backward()
    assert torch.isfinite(obs.grad).all()


# ---------------------------------------------------------------------------------------
# Gradients
# ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small64():
    observed, phases, pad, d = _scene(12, 34, 9.3, n_sub=2, noise=3.0, seed=5, dtype=torch.float64)
    return observed, phases, pad


def test_gradcheck_float64_observed_and_beta(small64):
    """Autograd vs central finite differences (torch.autograd.gradcheck, fast mode: random
    projections of the Jacobian) in float64 on the unquantised soft-argmax (the
    straight-through gradient is exactly this one). The integer argmax is piecewise
    constant, so a 1e-6 perturbation does not move it; rtol 1e-4 covers the float64
    rounding of the exp/rsqrt chain through ~100-term window sums."""
    observed, phases, pad = small64

    def fn(obs, beta):
        result = match(obs, phases, pad, 4, 16, 5, beta, 2, 5, 0.05, quantize=False, backend="torch", compile=False)
        return result.disparity

    obs = observed.clone().requires_grad_(True)
    beta = torch.tensor(15.0, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(fn, (obs, beta), eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_c_kernel_gradient_matches_float64_autograd(small64):
    """The C kernels' hand-written backward (float32) against float64 autograd (which the
    gradcheck above verifies against finite differences)."""
    if M.integer_search_backend() != "c":
        pytest.skip("no C compiler")
    observed, phases, pad = small64
    weights = torch.randn(observed.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def grads(obs, ph, backend):
        obs = obs.clone().requires_grad_(True)
        beta = torch.tensor(15.0, dtype=obs.dtype, requires_grad=True)
        result = match(obs, ph, pad, 4, 16, 5, beta, 2, 5, 0.05, quantize=False, backend=backend, compile=False)
        (result.disparity * weights.to(obs.dtype)).sum().backward()
        return obs.grad.double(), beta.grad.double()

    g32, b32 = grads(observed.float(), phases.float(), "c")
    g64, b64 = grads(observed, phases, "torch")
    rel = (g32 - g64).norm() / g64.norm()
    assert rel < 1e-3, f"relative error {rel:.2e}"  # float32 rounding in a ~100-term chain
    assert abs(float(b32 - b64)) <= 1e-3 * abs(float(b64)) + 1e-6


def test_finite_difference_beta_float32_c_path():
    """Central differences w.r.t. beta on the float32 C path (beta never moves the integer
    argmax, so the loss is smooth in beta). The observed-image gradient of this path is
    checked against float64 autograd above: image perturbations large enough to beat float32
    rounding also flip near-tie integer argmaxes, which makes a float32 pixel FD unreliable."""
    if M.integer_search_backend() != "c":
        pytest.skip("no C compiler")
    observed, phases, pad, _ = _scene(16, 48, 11.4, n_sub=2, noise=3.0, seed=7)
    weights = torch.linspace(-1, 1, observed.numel()).reshape(observed.shape)

    def loss(beta):
        result = match(observed, phases, pad, 4, 20, 7, beta, 2, 64, 0.05, quantize=False, compile=False)
        return (result.disparity * weights).sum()

    beta = torch.tensor(15.0, requires_grad=True)
    loss(beta).backward()
    with torch.no_grad():
        fd = (loss(15.25) - loss(14.75)) / 0.5
    # O(step^2) error ~1e-3 relative here; float32 rounding of the loss ~3e-5 / 0.5.
    assert abs(float(fd - beta.grad)) <= 1e-2 * abs(float(beta.grad)) + 2e-4, (float(fd), float(beta.grad))


def test_straight_through_gradient_equals_soft_gradient(sloped):
    observed, phases, pad, _ = sloped
    grads = []
    for quantize in (True, False):
        obs = observed.clone().requires_grad_(True)
        result = match(obs, phases, pad, 8, 30, 9, 15.0, 2, 64, 0.05, quantize=quantize, compile=False)
        result.disparity.sum().backward()
        grads.append(obs.grad)
    assert torch.equal(grads[0], grads[1])
    assert grads[0].abs().sum() > 0


def test_gradients_finite_on_flat_windows_unknown_reference_and_seams():
    """Flat (textureless) regions, saturated columns, reference columns that are unknown
    (NaN, stereo padding) and band seams: values and gradients stay finite."""
    height, width = 24, 64
    rng = np.random.default_rng(0)
    right = rng.random((height, width)).astype(np.float32)
    left = np.roll(right, 6, axis=1)
    left[:, 20:34] = 0.5  # flat block
    left[8:12, :] = 1.0  # flat rows across a band seam
    pad = 6 + 9 + 8
    phases = stereo_reference_phases(torch.from_numpy(right), 2, pad)
    assert torch.isnan(phases[:, :, :pad]).all()
    for backend in ("c", "torch"):
        if backend == "c" and M.integer_search_backend() != "c":
            continue
        obs = torch.from_numpy(left).requires_grad_(True)
        beta = torch.tensor(15.0, requires_grad=True)
        result = match(obs, phases, pad, 0, 14, 9, beta, 2, 8, 0.05, backend=backend, compile=False)
        assert torch.isfinite(result.disparity).all()
        (result.disparity.sum() + (result.disparity**2).mean()).backward()
        assert torch.isfinite(obs.grad).all() and torch.isfinite(beta.grad)
        conf = result.confidence.numpy()
        flat_rows = np.r_[0:4, 16:24]  # windows entirely inside the flat block
        assert (conf[flat_rows][:, 24:30] < 0.05).all(), "flat windows must be low-confidence"
        # Never matched against the unknown (NaN) padding: valid windows lie inside RIGHT.
        u = torch.arange(width, dtype=torch.float32)
        inside = (u - result.disparity.detach() - 4) >= -1e-4
        assert inside[result.valid].all(), "a valid match used reference columns outside the right image"
        assert not (result.valid[:, :6] & ((result.disparity[:, :6] - 6).abs() < 0.5)).any()


def test_gradient_wrt_reference_phases_when_they_require_grad():
    """The disparities' gradient with respect to the reference phases is the derivative a central difference along a
    random direction gives, on the pixels that keep their validity and their best integer match over the step (a
    change of match moves a disparity by a large fraction of a pixel, not by step x gradient)."""
    observed, phases, pad, _ = _scene(12, 40, 8.5, n_sub=1, noise=2.0, seed=9)

    def disparity(reference):
        result = match(observed, reference, pad, 3, 14, 5, 15.0, 1, 64, 0.05, compile=False, quantize=False)
        return result.disparity, result.valid

    direction, step = torch.randn(phases.shape, generator=torch.Generator().manual_seed(1)), 1e-4
    with torch.no_grad():
        (up, valid_up), (down, valid_down) = disparity(phases + step * direction), disparity(phases - step * direction)
    ph = phases.clone().requires_grad_(True)
    depth, valid = disparity(ph)
    kept = (valid & valid_up & valid_down & ((up - down).abs() < 0.05)).float()
    assert kept.sum() > 300
    (depth * kept).sum().backward()
    assert torch.isfinite(ph.grad).all()
    numeric = float(((up - down) * kept).sum()) / (2 * step)
    analytic = float((ph.grad * direction).sum())
    assert abs(analytic) > 100 and analytic == pytest.approx(numeric, rel=0.02), (analytic, numeric)


# ---------------------------------------------------------------------------------------
# Memory
# ---------------------------------------------------------------------------------------
class _PeakTensorMemory(TorchDispatchMode):
    """Peak bytes of live tensor storages allocated inside the mode (views of existing
    storages, e.g. of the cached reference, are not allocations)."""

    def __init__(self):
        super().__init__()
        self.live = 0
        self.peak = 0
        self._seen = set()

    def _track(self, tensor):
        storage = tensor.untyped_storage()
        key = storage.data_ptr()
        if key in self._seen or storage.nbytes() == 0:
            return
        self._seen.add(key)
        self.live += storage.nbytes()
        self.peak = max(self.peak, self.live)
        nbytes = storage.nbytes()

        def release(key=key, nbytes=nbytes):
            self.live -= nbytes
            self._seen.discard(key)

        weakref.finalize(storage, release)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        inputs = {t.untyped_storage().data_ptr() for t in tree_flatten((args, kwargs))[0] if isinstance(t, torch.Tensor)}
        for item in tree_flatten(out)[0]:
            # Views share their input's storage: only new allocations count.
            if isinstance(item, torch.Tensor) and item.untyped_storage().data_ptr() not in inputs:
                self._track(item)
        return out


def test_band_rows_bound_the_cost_volume():
    """torch backend: the (row, column, disparity) volume exists one band at a time, so peak
    tensor memory follows band_rows and stays far below that of a whole-image volume."""
    height, width, d_max = 160, 120, 40
    observed, phases, pad, _ = _scene(height, width, 20.0, n_sub=2, pad=d_max + 16, seed=2)
    reference._REF_CACHE.clear()
    # Reference tensors (and the torch path's per-candidate layout, built on its first use)
    # are per sensor, not per frame: build them before measuring.
    reference._prepare_reference(phases, pad, 9, 2, 4 + SEARCH_LANES).torch_candidates()
    peaks = {}
    for rows in (4, 16, height):
        with _PeakTensorMemory() as mode:
            match(observed, phases, pad, 0, d_max, 9, 15.0, 2, rows, 0.05, backend="torch", compile=False)
        peaks[rows] = mode.peak
    full_volume = height * width * (d_max + 1) * 4  # one float32 score volume of the whole image
    assert peaks[height] > 2 * full_volume, peaks  # unbanded: several whole-image volumes
    assert peaks[4] < 0.5 * full_volume, (peaks, full_volume)  # banded: image-sized buffers only
    assert peaks[4] < peaks[16] < peaks[height]


def test_c_path_memory_does_not_grow_with_the_disparity_range():
    """The C integer search streams over disparities: no cost volume at all, so peak tensor
    memory is independent of the number of disparities (61 here would be a 3.7 MB volume)."""
    if M.integer_search_backend() != "c":
        pytest.skip("no C compiler")
    height, width = 96, 160
    observed, phases, pad, _ = _scene(height, width, 15.0, n_sub=2, pad=76, seed=2)
    peaks = {}
    for d_max in (20, 60):
        reference._prepare_reference(phases, pad, 9, 2, 4 + 8)
        with _PeakTensorMemory() as mode:
            match(observed, phases, pad, 0, d_max, 9, 15.0, 2, 32, 0.05, compile=False)
        peaks[d_max] = mode.peak
    assert peaks[60] < 1.1 * peaks[20], peaks
    # What remains is the refinement's: O(pixels x 13 sub-pixel candidates (K +- 1.5 px in
    # quarter steps)), ~12 floats each.
    assert peaks[60] < 16 * height * width * 13 * 4, peaks


def test_reference_cache_grows_with_the_phases_not_with_the_candidates():
    """The cached reference holds the S phases in a few layouts (and their window statistics),
    not one copy per refinement candidate (C = 3S + 1 of them: 13 at n_sub 2, 49 at n_sub 4).
    Measured bytes of the tensors the cache keeps, and the build's peak, in units of the
    phases' own size: a per-candidate layout would be ~C/S copies per layout (the previous
    one held 19-21 and peaked at 40-43)."""
    height, width = 64, 160
    held, peak = {}, {}
    for n_sub in (2, 4):
        observed, phases, pad, _ = _scene(height, width, 15.0, n_sub=n_sub, pad=40, seed=2)
        reference._REF_CACHE.clear()
        with _PeakTensorMemory() as mode:
            ref = reference._prepare_reference(phases, pad, 9, n_sub, 4 + 8)
        size = phases.numel() * phases.element_size()
        held[n_sub], peak[n_sub] = mode.live, mode.peak
        # two layouts of the phases (the forward one 8 / S copies for S < 8: aligned vectors),
        # two float statistics, a byte mask, the integer stage: measured 7.3 (S = 4), 5.2 (S = 16)
        assert mode.live < 8 * size, (n_sub, mode.live / size)
        assert mode.peak < 12 * size, (n_sub, mode.peak / size)  # built one phase at a time
        if M.integer_search_backend() == "c":  # the C path never builds the torch layout
            match(observed, phases, pad, 0, 20, 9, 15.0, n_sub, 32, 0.05, refine_level=n_sub)
            assert reference._prepare_reference(phases, pad, 9, n_sub, 4 + 8) is ref and ref._torch is None
    assert held[4] <= 1.05 * 4 * held[2], held  # S grows 4x, C = 3S + 1 would too: bytes follow S
    reference._REF_CACHE.clear()


# ---------------------------------------------------------------------------------------
# Reference phases and input checks
# ---------------------------------------------------------------------------------------
def test_stereo_reference_phases_layout():
    right = torch.arange(5 * 12, dtype=torch.float32).reshape(5, 12) % 7 + torch.rand(5, 12)
    pad = 4
    phases = stereo_reference_phases(right, 1, pad)
    assert phases.shape == (2, 5, 16)
    assert torch.isnan(phases[:, :, :pad]).all()
    assert torch.allclose(phases[0, :, pad:], right)  # phase 0: R(j - pad)
    # phase 1 at column j holds R(j - pad - 1/2); a linear ramp is reproduced exactly by cubic
    ramp = torch.arange(12, dtype=torch.float32).expand(5, 12).contiguous()
    half = stereo_reference_phases(ramp, 1, pad)[1]
    assert torch.allclose(half[:, pad + 2 : -1], ramp[:, 2:-1] - 0.5, atol=1e-5)
    assert torch.isnan(half[:, pad]).all()  # R(-1/2) is outside the image


def test_input_validation():
    observed = torch.rand(16, 40)
    phases = torch.rand(4, 16, 60)
    with pytest.raises(ValueError, match="reference_phases"):
        match(observed, phases[:2], 20, 0, 8, 5, 15.0, 2)
    with pytest.raises(ValueError, match="block"):
        match(observed, phases, 20, 0, 8, 4, 15.0, 2)
    with pytest.raises(ValueError, match="pad"):
        match(observed, phases, 20, 0, 19, 5, 15.0, 2)
    with pytest.raises(ValueError, match="range"):
        match(observed, phases, 20, 5, 4.5, 5, 15.0, 2)


# ---------------------------------------------------------------------------------------
# Validity at depth edges: the confirmed-match rule (preset key confirmed_match_zncc)
# ---------------------------------------------------------------------------------------
def test_windows_across_a_depth_edge_keep_one_of_its_surfaces():
    """A vertical depth edge (near surface d = 24 px on the left, far d = 14 px on the right): a
    window across it sees both, its ZNCC has two peaks and fails the uniqueness test; confirmed by
    a unique neighbour on the same surface it is kept, with that surface's disparity."""
    height, width, edge = 40, 120, 60
    disparity = np.where(np.arange(width) < edge, 24.0, 14.0)[None].repeat(height, 0)
    observed, phases, pad, _ = _scene(height, width, disparity, n_sub=2, noise=6.0, seed=4)

    def run(confirmed_match_zncc):
        return match(observed, phases, pad, 5, pad - 12, 9, 15.0, 2, 64, 0.15, compile=False,
                     confirmed_match_zncc=confirmed_match_zncc)  # fmt: skip

    band = (slice(4, -4), slice(edge - 8, edge + 8))  # the windows that straddle the edge
    uniqueness_only, device = run(1.0), run(0.4)
    kept = {name: float(r.valid[band].float().mean()) for name, r in (("off", uniqueness_only), ("on", device))}
    assert kept["off"] < 0.9 and kept["on"] > 0.95, kept  # measured 0.865 and 0.963
    assert (device.valid | ~uniqueness_only.valid).all()  # the rule only adds pixels
    d = device.disparity.detach()[band][device.valid[band]]
    on_a_surface = torch.minimum((d - 24).abs(), (d - 14).abs()) <= 1
    assert on_a_surface.float().mean() > 0.97


def test_repeated_texture_stays_invalid_with_the_confirmed_match_rule():
    """Texture that repeats every 8 px matches equally well at d and d +- 8 px (best and second ZNCC
    both ~1): ambiguous, however strong. Next to uniquely textured pixels at the same disparity, only
    windows whose best peak is that disparity are confirmed; farther than a window from them, nothing."""
    height, width, period, true_d, seam = 32, 120, 8, 20.3, 48
    pad = 60
    xs, ys, amp = _dots(height, 0, period, seed=5)
    tiles = range(-(pad + 8) // period - 1, (width + 8) // period + 2)
    periodic = (np.concatenate([xs + k * period for k in tiles]), np.tile(ys, len(tiles)), np.tile(amp, len(tiles)))
    unique = _dots(height, -pad - 3, width + 3, seed=6)
    x_seam = seam - true_d  # pattern coordinate of the seam: unique texture left of it, repeated right of it

    def texture(x, y):
        return np.where(x < x_seam, _render(unique, x, y), _render(periodic, x, y))

    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    observed = 40 + 800 * texture(u - true_d, v) + np.random.default_rng(1).normal(0, 2.0, u.shape)
    vj, j = np.mgrid[0:height, 0 : width + pad].astype(np.float64)
    phases = np.stack([40 + 800 * texture(j - pad - s / 4, vj) for s in range(4)])
    observed, phases = torch.tensor(observed, dtype=torch.float32), torch.tensor(phases, dtype=torch.float32)
    for confirmed_match_zncc in (1.0, 0.4, 0.0):
        result = match(observed, phases, pad, 5, pad - 12, 9, 15.0, 2, 64, 0.15, compile=False,
                       confirmed_match_zncc=confirmed_match_zncc)  # fmt: skip
        deep = (slice(4, -4), slice(seam + 9 + 4, width - 4))  # windows that see only repeated texture
        assert float(result.best_zncc[deep].median()) > 0.9  # strong: a best-ZNCC-only rule would keep them
        assert not result.valid[deep].any(), confirmed_match_zncc
        d = result.disparity.detach()[result.valid]
        assert ((d - true_d).abs() <= 1).all()  # nothing valid at a wrong period


@pytest.mark.parametrize("backend", ["c", "torch"])
def test_second_peak_of_repeated_texture_is_one_period_away(backend):
    """Texture repeating every 8 px matches at d and d +- 8 px (not unique): the integer search reports the
    second peak's disparity one period from the best (C kernel and torch twin alike)."""
    if backend == "c" and M.integer_search_backend() != "c":
        pytest.skip("no C compiler")
    height, width, period, true_d, pad = 24, 80, 8, 20.0, 48
    xs, ys, amp = _dots(height, 0, period, seed=5)
    tiles = range(-(pad + 8) // period - 1, (width + 8) // period + 2)
    periodic = (np.concatenate([xs + k * period for k in tiles]), np.tile(ys, len(tiles)), np.tile(amp, len(tiles)))
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    observed = torch.tensor(40 + 800 * _render(periodic, u - true_d, v), dtype=torch.float32)
    vj, j = np.mgrid[0:height, 0 : width + pad].astype(np.float64)
    phases = torch.tensor(np.stack([40 + 800 * _render(periodic, j - pad - s / 4, vj) for s in range(4)]),
                          dtype=torch.float32)  # fmt: skip
    result = match(observed, phases, pad, 5, pad - 12, 9, 15.0, 2, 64, 0.15, compile=False, backend=backend,
                   confirmed_match_zncc=0.4)  # fmt: skip
    inner = (slice(4, -4), slice(4, -4))
    gap = (result.second_peak_px[inner].long() - result.peak_px[inner]).abs()
    assert float(result.second_zncc[inner].median()) > 0.9
    assert ((gap - period).abs() <= 1).float().mean() > 0.99, gap.unique()


def test_paper_presets_keep_the_uniqueness_test_alone():
    from ddsgen.preset import load_preset

    for name in ("kinect_v1_paper", "matterport_pro2"):
        assert load_preset(name).confirmed_match_zncc == 1.0  # the neutral value: the rule is off
    assert load_preset("kinect_v1").confirmed_match_zncc < 1.0


def test_c_and_torch_confirmations_agree_on_surfaces_with_edges_and_noise():
    """The confirmed-match rule's C kernel (stops at the first agreeing neighbour) and its torch twin (gathers the
    whole window) confirm the same pixels for both peaks, at image borders too; a peak two px off a unique
    neighbour is not confirmed, one px off is."""
    if M.integer_search_backend() != "c":
        pytest.skip("no C compiler")
    g = torch.Generator().manual_seed(3)
    height, width, block = 60, 90, 9
    columns = torch.arange(width)
    k_int = torch.where(columns < 45, 20, 35).expand(height, width).clone()  # two surfaces, an edge at column 45
    k_int += torch.randint(-1, 2, (height, width), generator=g)  # +-1 px of matching noise
    unique = torch.rand(height, width, generator=g) < 0.2
    candidates = ~unique & (torch.rand(height, width, generator=g) < 0.5)
    second = torch.where(torch.rand(height, width, generator=g) < 0.5, 55 - k_int, torch.full_like(k_int, -1))
    results = {backend: M._confirmed_by_a_unique_neighbour(k_int, unique, candidates, block, (k_int, second),
                                                           backend=backend) for backend in ("c", "torch")}  # fmt: skip
    for c_out, torch_out in zip(results["c"], results["torch"]):
        assert torch.equal(c_out, torch_out)
    by_best, by_second = results["c"]
    assert int(by_best.sum()) > 0.9 * int(candidates.sum())  # every surface has unique matches nearby
    assert not bool((by_best & ~candidates).any()) and not bool((by_second & ~candidates).any())
    # One unique neighbour at disparity 10 in an empty field: 9 and 11 agree with it, 8 does not.
    lone = torch.zeros(height, width, dtype=torch.bool)
    lone[30, 40] = True
    peaks = tuple(torch.full((height, width), d) for d in (9, 11, 8))
    for backend in ("c", "torch"):
        near = M._confirmed_by_a_unique_neighbour(torch.full((height, width), 10), lone, ~lone, block, peaks,
                                                  backend=backend)  # fmt: skip
        assert [bool(p[30, 44]) for p in near] == [True, True, False]  # 4 px away: within the 9-px window
        assert not any(bool(p[30, 45]) for p in near)  # 5 px away: outside it


@pytest.mark.parametrize("block, min_confidence, confirmed", [(9, 0.05, 0.35), (7, 0.1, 0.5), (9, 0.05, 1.0)])
def test_the_c_validity_is_the_torch_definition_bit_for_bit(block, min_confidence, confirmed):
    """csrc/validity.c gives :func:`M._validity_of_peaks`' maps bit for bit: ZNCCs beyond [0, 1], no peak found,
    no second peak, two surfaces with +-1 px of noise (confirmations by the best and by the second peak), the
    blind border columns, confidences on the thresholds; and on a rendered-like IR pair's real search output."""
    from ddsgen.sensor.matcher.validity_kernel import match_validity_c

    if match_validity_c(*(torch.zeros(3, 3),) * 2, torch.zeros(3, 3, dtype=torch.int64),
                        torch.zeros(3, 3, dtype=torch.int32), 5, 0, 1, 0.05, 1.0) is None:  # fmt: skip
        pytest.skip("no C compiler")
    g = torch.Generator().manual_seed(5)
    height, width, k_hi, k_lo = 50, 80, 60, 3
    base = torch.where(torch.arange(width) < 40, 20, 35).expand(height, width)
    arg = (k_hi - base - torch.randint(-1, 2, (height, width), generator=g)).to(torch.int64)
    arg[torch.rand(height, width, generator=g) < 0.05] = -1
    arg2 = torch.where(torch.rand(height, width, generator=g) < 0.5, k_hi - (55 - base), -1).to(torch.int32)
    wrong = torch.rand(height, width, generator=g) < 0.15  # a wrong best peak; the surface's is the second
    arg2 = torch.where(wrong, k_hi - base - torch.randint(-3, 4, (height, width), generator=g), arg2).to(torch.int32)
    arg = torch.where(wrong, k_hi - torch.randint(42, 56, (height, width), generator=g), arg)
    best = torch.rand(height, width, generator=g) * 1.3 - 0.1
    second = best - torch.rand(height, width, generator=g) * 0.2
    second[:, ::9] = best[:, ::9] - min_confidence  # confidences on the threshold (in float32 arithmetic)
    best[::7] = confirmed  # ZNCCs on the confirmation threshold
    cases = [(best, second, arg, arg2)]
    # A real search: a slanted IR-like random texture against itself shifted by 20 px.
    texture = torch.rand(40, 140, generator=g)
    observed = texture[:, 20:120].contiguous()
    phases = texture[None, :, :].expand(8, 40, 140).contiguous()
    pad = 40
    reference_phases = torch.nn.functional.pad(phases[:, :, :120], (pad - 20, 0))
    with torch.no_grad():
        ref = M._prepare_reference(reference_phases, pad, block, 3, block // 2 + SEARCH_LANES, 3)
        x = (observed - observed.mean()) / observed.std()
        o_pad, osum, oinv = M._ObservedStatsC.apply(x, block)
        r0 = pad + ref.offset - block // 2 - 30
        cases.append(kernel._integer_search_c(kernel._load_kernel(), o_pad, ref, osum, oinv, block, r0, 28, confirmed,
                                              min_confidence))  # fmt: skip
    results = []
    for i, (b, s, a, a2) in enumerate(cases):
        hi, lo = (k_hi, k_lo) if i == 0 else (30, 3)
        fast = match_validity_c(b, s, a, a2, hi, lo, block, min_confidence, confirmed)
        definition = M._validity_of_peaks(b, s, a, a2, hi, lo, block, min_confidence, confirmed)
        for got, expected in zip(fast, definition):
            assert got.dtype == expected.dtype and torch.equal(got, expected)
        assert fast[3].any() and not fast[3].all()
        results.append(fast)
    _, _, confidence, valid, k_int, _ = results[0]
    clipped = best.clamp(0, 1) - second.clamp(0, 1)
    by_rule = valid & (clipped < min_confidence)  # valid only by a confirmation
    took_second = k_int != torch.where(arg >= 0, k_hi - arg, k_lo)
    if confirmed < 1.0:
        assert by_rule.sum() > 50 and took_second.sum() > 5 and (took_second <= by_rule).all()
    else:
        assert not by_rule.any() and not took_second.any()
