"""tnf.metrics against hand-computed values and an independent SSIM written here with scipy."""

import numpy as np
import pytest
import torch
from scipy.ndimage import correlate1d

from tnf.metrics import mse, ssim


def _images(seed: int, n: int = 2, size: int = 128) -> torch.Tensor:
    """Smooth random uint8 images [n, 3, size, size] (blurred noise, like tactile images are)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, size // 8, size // 8, generator=g)
    x = torch.nn.functional.interpolate(x, size=(size, size), mode="bilinear", align_corners=False)
    return (40 + 170 * x + 20 * torch.rand(n, 3, size, size, generator=g)).round().byte()


def _reference_ssim(a: np.ndarray, b: np.ndarray, valid: bool = False) -> float:
    """SSIM of two [3, H, W] 0-255 images (Wang et al. 2004): Gaussian window 11 / sigma 1.5, K1 0.01, K2 0.03,
    L 255, averaged over pixels and channels. Borders: the image is mirrored (d c b | a b c d) and every pixel's
    SSIM is averaged, the convention of tnf's metric (torchmetrics); ``valid=True`` averages only pixels whose
    window lies inside the image (skimage's convention)."""
    r = np.arange(11) - 5
    w = np.exp(-(r**2) / (2 * 1.5**2))
    w /= w.sum()

    def blur(x):
        y = correlate1d(correlate1d(x, w, axis=0, mode="mirror"), w, axis=1, mode="mirror")
        return y[5:-5, 5:-5] if valid else y

    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    vals = []
    for x, y in zip(a.astype(np.float64), b.astype(np.float64), strict=True):
        mx, my = blur(x), blur(y)
        sxx, syy, sxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
        s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))
        vals.append(s.mean())
    return float(np.mean(vals))


def test_identical_images_give_ssim_one_and_mse_zero():
    x = _images(0)
    assert torch.allclose(ssim(x, x), torch.ones(2), atol=1e-5)
    assert torch.equal(mse(x, x), torch.zeros(2))


def test_constant_offset_gives_known_mse():
    x = _images(1)
    y = x + 10  # values stay below 255, so no clipping
    assert torch.allclose(mse(x, y), torch.full((2,), 100.0))
    # the same images in tnf's [-1, 1] float range give the same MSE on the 0-255 scale
    xf, yf = x.float() / 127.5 - 1, y.float() / 127.5 - 1
    assert torch.allclose(mse(xf, yf), torch.full((2,), 100.0))
    assert (ssim(x, y) < 1).all()


def test_mse_in_range_0_to_65025():
    black = torch.zeros(1, 3, 128, 128, dtype=torch.uint8)
    white = torch.full((1, 3, 128, 128), 255, dtype=torch.uint8)
    assert mse(black, white).item() == 65025.0


@pytest.mark.parametrize("seed", [2, 3])
def test_ssim_agrees_with_independent_implementation(seed):
    a, b = _images(seed), _images(seed + 100)
    b = ((a.float() + b.float()) / 2).round().byte()  # partly similar, SSIM well inside (0, 1)
    ours = ssim(a, b)
    ref = [_reference_ssim(a[i].numpy(), b[i].numpy()) for i in range(len(a))]
    assert 0.2 < min(ref) < 0.95
    np.testing.assert_allclose(ours.numpy(), ref, atol=1e-4)
    # the border convention moves SSIM by far less than the gaps between methods in the paper (>= 0.01)
    valid = [_reference_ssim(a[i].numpy(), b[i].numpy(), valid=True) for i in range(len(a))]
    np.testing.assert_allclose(ours.numpy(), valid, atol=0.01)


def test_images_are_compared_at_128():
    big = _images(4, n=1, size=256)
    small = torch.nn.functional.interpolate(big.float(), size=(128, 128), mode="bilinear", antialias=True)
    assert ssim(big, small.round().byte()).item() > 0.999


def test_metrics_inside_bf16_autocast_equal_float32_metrics():
    # A bf16-mixed trainer validates inside autocast: SSIM's variances of values near 255 in bfloat16 would
    # cancel to noise (validation SSIM 0.66 where the float32 figure was 0.92).
    g = torch.Generator().manual_seed(0)
    real = (torch.rand(4, 3, 128, 128, generator=g) * 1.6 - 0.8).clamp(-1, 1)
    fake = (real + 0.05 * torch.randn(4, 3, 128, 128, generator=g)).clamp(-1, 1)
    ref_ssim, ref_mse = ssim(fake, real), mse(fake, real)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        s, m = ssim(fake, real), mse(fake, real)
    assert s.dtype == torch.float32 and torch.equal(s, ref_ssim)
    assert torch.equal(m, ref_mse)


def test_ssim_equals_torchmetrics_which_scored_the_committed_results():
    # tnf's reports before its own implementation were scored with torchmetrics' SSIM (same window,
    # constants and mirrored borders): both must give the same figures.
    from torchmetrics.functional.image import structural_similarity_index_measure

    a, b = _images(7, n=4), _images(8, n=4)
    b = ((a.float() * 3 + b.float()) / 4).round().byte()
    ref = structural_similarity_index_measure(
        a.float(), b.float(), gaussian_kernel=True, kernel_size=11, sigma=1.5, data_range=255.0, reduction="none"
    )
    assert torch.allclose(ssim(a, b), ref, atol=1e-5)


def test_ssim_refuses_images_smaller_than_its_window():
    from tnf.metrics import ssim_unquantised

    with pytest.raises(ValueError, match="larger than 5 px"):
        ssim_unquantised(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 4))


def test_ssim_loss_in_float32_matches_float64_in_value_and_gradient():
    # The training loss computes the window's statistics in float32 (centred values, exact products); the metric
    # in float64. A prediction close to the truth is where the variances cancel most.
    from tnf.metrics import _ssim, ssim_unquantised

    real = _images(3, n=3).float() / 127.5 - 1
    noise = torch.randn(real.shape, generator=torch.Generator().manual_seed(4))
    pred = (real + 0.01 * noise).requires_grad_(True)
    saved = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision("high")  # what GPU training sets: TF32 products
    try:
        loss32 = ssim_unquantised(pred, real)
        (grad32,) = torch.autograd.grad(loss32.sum(), pred)
        assert torch.get_float32_matmul_precision() == "high"  # restored after both passes
    finally:
        torch.set_float32_matmul_precision(saved)
    loss64 = _ssim((pred.double() + 1) / 2, (real.double() + 1) / 2, 1.0, torch.float64)
    (grad64,) = torch.autograd.grad(loss64.sum(), pred)
    assert 0.5 < loss64.min() < 0.999
    assert torch.allclose(loss32, loss64, atol=1e-6)
    assert ((grad32.double() - grad64).norm() / grad64.norm()) < 1e-4


@pytest.mark.parametrize("offset", [0, 1, 40])
def test_ssim_metric_in_float32_matches_float64(offset):
    # The metric computes its statistics in float32 (centred values, exact window products, whatever the matmul
    # precision a GPU trainer set); float64 is the reference. Near-identical images (offset 0, 1) are where the
    # variances cancel most; bright images (values near 255) where uncentred float32 would lose the most digits.
    from tnf.metrics import _prepare, _ssim

    a = _images(5, n=4)
    noise = torch.randint(-offset, offset + 1, a.shape, generator=torch.Generator().manual_seed(6))
    b = (a.int() + noise + 60).clamp(0, 255).byte()
    a = (a.int() + 60).clamp(0, 255).byte()
    saved = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision("high")
    try:
        ours = ssim(a, b)
    finally:
        torch.set_float32_matmul_precision(saved)
    ref = _ssim(_prepare(a), _prepare(b), 255.0, torch.float64)  # computed in float64, returned as float32
    assert ours.dtype == torch.float32
    assert offset > 0 or torch.equal(ref, torch.ones(4))
    assert 0.2 < ref.min() and (offset == 0 or ref.max() < 0.9999)
    assert torch.allclose(ours, ref, atol=1e-6, rtol=0)
