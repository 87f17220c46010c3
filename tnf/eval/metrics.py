"""Image metrics shared by training (validation) and evaluation, so both report the same numbers.

Following the paper: images are compared as 8-bit RGB at 128 x 128; SSIM uses a Gaussian window of 11
pixels with sigma 1.5 and data range 255, averaged over the RGB channels; MSE is on the 0-255 scale
(range 0-65025).

Both ignore autocast (a bf16-mixed trainer's validation). SSIM's local statistics are computed in float64:
its variances E[x^2] - E[x]^2 of values near 255 cancel to noise in bfloat16, and would lose most of their
digits in the TF32 matrix products that GPU training switches on for float32.
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F

SIZE = 128


def to_uint8_scale(x: torch.Tensor) -> torch.Tensor:
    """[B, 3, H, W] images -> float on the 0-255 scale, quantised as 8-bit images are.

    Accepts uint8, or float in [-1, 1] (tnf's network range).
    """
    if x.dtype == torch.uint8:
        return x.float()
    return ((x.float().clamp(-1, 1) + 1) * 127.5).round()


def _prepare(x: torch.Tensor) -> torch.Tensor:
    x = to_uint8_scale(x)
    if x.shape[-2:] != (SIZE, SIZE):
        x = F.interpolate(x, size=(SIZE, SIZE), mode="bilinear", align_corners=False, antialias=True).round()
    return x


WINDOW, SIGMA, K1, K2 = 11, 1.5, 0.01, 0.03


@functools.lru_cache(maxsize=8)
def _blur_matrix(n: int, device: torch.device) -> torch.Tensor:
    """[n, n] matrix M with (M @ x) the Gaussian window applied along x's first axis of length n, over mirrored
    borders (d c b | a b c d). One matrix product per axis instead of a depthwise convolution, which is slow on
    CPUs."""
    r = torch.arange(WINDOW) - (WINDOW - 1) // 2
    w = torch.exp(-(r.double() ** 2) / (2 * SIGMA**2))
    w = w / w.sum()
    i = torch.arange(n).repeat_interleave(WINDOW)
    j = (torch.arange(n)[:, None] + r[None, :]).flatten().abs()  # mirror at 0
    j = torch.where(j > n - 1, 2 * (n - 1) - j, j)  # mirror at n - 1
    m = torch.zeros(n, n, dtype=torch.float64).index_put_((i, j), w.repeat(n), accumulate=True)
    return m.to(device)


def _ssim(p: torch.Tensor, t: torch.Tensor, data_range: float) -> torch.Tensor:
    """Per-image SSIM, [B] float32, of float [B, C, H, W] images: local statistics under the Gaussian window
    over mirrored borders (in float64), every pixel's SSIM averaged over pixels and channels."""
    b, _, h, w = p.shape
    if min(h, w) <= WINDOW // 2:
        raise ValueError(f"SSIM needs images larger than {WINDOW // 2} px, got {h} x {w}")
    p, t = p.double(), t.double()
    x = torch.cat([p, t, p * p, t * t, p * t])
    x = _blur_matrix(h, p.device) @ x @ _blur_matrix(w, p.device).T
    mp, mt, epp, ett, ept = x.split(b)
    vp, vt, cov = (epp - mp * mp).clamp_min(0), (ett - mt * mt).clamp_min(0), ept - mp * mt
    c1, c2 = (K1 * data_range) ** 2, (K2 * data_range) ** 2
    s = ((2 * mp * mt + c1) * (2 * cov + c2)) / ((mp * mp + mt * mt + c1) * (vp + vt + c2))
    return s.flatten(1).mean(1).float()


def ssim(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-image SSIM, [B], of [B, 3, H, W] images (uint8 or [-1, 1] floats), mean over channels."""
    with torch.autocast(pred.device.type, enabled=False):
        return _ssim(_prepare(pred), _prepare(target), 255.0)


def ssim_unquantised(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-image SSIM, [B], of [-1, 1] float images as :func:`ssim` computes it but without the 8-bit
    rounding, so it has gradients (a training loss). Equal to :func:`ssim` on 128 px images that are already
    8-bit values."""
    with torch.autocast(pred.device.type, enabled=False):
        # SSIM is unchanged by scaling the images and their range together: [0, 1] with range 1 is 0-255 / 255.
        return _ssim((pred.float() + 1) / 2, (target.float() + 1) / 2, 1.0)


def mse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-image MSE on the 0-255 scale, [B], of [B, 3, H, W] images (uint8 or [-1, 1] floats)."""
    with torch.autocast(pred.device.type, enabled=False):
        p, t = _prepare(pred), _prepare(target)
        return ((p - t) ** 2).flatten(1).mean(1)
