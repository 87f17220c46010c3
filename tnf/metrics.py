"""Image metrics shared by training (validation) and evaluation, so both report the same numbers.

Following the paper: images are compared as 8-bit RGB at 128 x 128; SSIM uses a Gaussian window of 11
pixels with sigma 1.5 and data range 255, averaged over the RGB channels; MSE is on the 0-255 scale
(range 0-65025).

Both ignore autocast (a bf16-mixed trainer's validation). SSIM's local statistics are computed in float32 on
values centred on zero, with the window's products in full float32 precision (not the TF32 that GPU training
switches on): their variances E[x^2] - E[x]^2 cancel to noise in bfloat16 and lose most of their digits in TF32.
The metric (:func:`ssim`) and the training loss (:func:`ssim_unquantised`) both do so; the metric is within 1e-6
of float64 per image, and 3.5x faster than float64 on a CPU. :func:`ssim_map` keeps float64.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator
from contextlib import contextmanager

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


@functools.lru_cache(maxsize=16)
def _blur_matrix(n: int, device: torch.device, dtype: torch.dtype = torch.float64) -> torch.Tensor:
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
    return m.to(device, dtype)


@contextmanager
def exact_fp32_matmul() -> Iterator[None]:
    """float32 matrix products in full precision (not TF32) inside the block; the caller's setting after it."""
    saved = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision("highest")
    try:
        yield
    finally:
        torch.set_float32_matmul_precision(saved)


class _Window(torch.autograd.Function):
    """The Gaussian window over both image axes, ``M_h @ x @ M_w^T``, with exact float32 products in the forward
    and the backward pass (autograd would run the backward's products with whatever precision is set then)."""

    @staticmethod
    def forward(ctx: torch.autograd.function.FunctionCtx, x: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        mh, mw = _blur_matrix(x.shape[-2], x.device, x.dtype), _blur_matrix(x.shape[-1], x.device, x.dtype)
        ctx.save_for_backward(mh, mw)
        with exact_fp32_matmul():
            return mh @ x @ mw.T

    @staticmethod
    def backward(ctx: torch.autograd.function.FunctionCtx, grad: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        mh, mw = ctx.saved_tensors  # type: ignore[attr-defined]
        with exact_fp32_matmul():
            return mh.T @ grad @ mw


def _ssim(p: torch.Tensor, t: torch.Tensor, data_range: float, dtype: torch.dtype) -> torch.Tensor:
    """Per-image SSIM, [B] float32, of float [B, C, H, W] images: every pixel's SSIM (:func:`_ssim_map`)
    averaged over pixels and channels."""
    return _ssim_map(p, t, data_range, dtype).flatten(1).mean(1).float()


def _ssim_map(p: torch.Tensor, t: torch.Tensor, data_range: float, dtype: torch.dtype) -> torch.Tensor:
    """Per-pixel SSIM, [B, C, H, W] in ``dtype``, of float [B, C, H, W] images: local statistics under the
    Gaussian window over mirrored borders (in ``dtype``, of values centred on zero)."""
    b, _, h, w = p.shape
    if min(h, w) <= WINDOW // 2:
        raise ValueError(f"SSIM needs images larger than {WINDOW // 2} px, got {h} x {w}")
    # Centred values keep E[x^2] - E[x]^2 to the digits of the variance itself; the means are shifted back for
    # the luminance term, which is not shift-invariant.
    mid = data_range / 2
    p = p.to(dtype, memory_format=torch.contiguous_format) - mid
    t = t.to(dtype, memory_format=torch.contiguous_format) - mid
    x = _Window.apply(torch.cat([p, t, p * p, t * t, p * t]))
    mp, mt, epp, ett, ept = x.split(b)
    vp, vt, cov = (epp - mp * mp).clamp_min(0), (ett - mt * mt).clamp_min(0), ept - mp * mt
    mp, mt = mp + mid, mt + mid
    c1, c2 = (K1 * data_range) ** 2, (K2 * data_range) ** 2
    return ((2 * mp * mt + c1) * (2 * cov + c2)) / ((mp * mp + mt * mt + c1) * (vp + vt + c2))


def ssim(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-image SSIM, [B], of [B, 3, H, W] images (uint8 or [-1, 1] floats), mean over channels."""
    with torch.autocast(pred.device.type, enabled=False):
        return _ssim(_prepare(pred), _prepare(target), 255.0, torch.float32)


def ssim_unquantised(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-image SSIM, [B], of [-1, 1] float images as :func:`ssim` computes it but without the 8-bit
    rounding, so it has gradients (a training loss). Equal to :func:`ssim` on 128 px images that are already
    8-bit values."""
    with torch.autocast(pred.device.type, enabled=False):
        # SSIM is unchanged by scaling the images and their range together: [0, 1] with range 1 is 0-255 / 255.
        return _ssim((pred.float() + 1) / 2, (target.float() + 1) / 2, 1.0, torch.float32)


def ssim_map(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM, [B, H, W] float64, of [B, 3, H, W] images (uint8 or [-1, 1] floats) at their own size
    (not resized to 128 px), mean over channels: its mean over a region is that region's SSIM."""
    with torch.autocast(pred.device.type, enabled=False):
        return _ssim_map(to_uint8_scale(pred), to_uint8_scale(target), 255.0, torch.float64).mean(1)


def mse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-image MSE on the 0-255 scale, [B], of [B, 3, H, W] images (uint8 or [-1, 1] floats)."""
    with torch.autocast(pred.device.type, enabled=False):
        p, t = _prepare(pred), _prepare(target)
        return ((p - t) ** 2).flatten(1).mean(1)
