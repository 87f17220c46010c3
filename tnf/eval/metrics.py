"""Image metrics shared by training (validation) and evaluation, so both report the same numbers.

Following the paper: images are compared as 8-bit RGB at 128 x 128; SSIM uses a Gaussian window of 11
pixels with sigma 1.5 and data range 255, averaged over the RGB channels; MSE is on the 0-255 scale
(range 0-65025).

Both compute in float32 even inside an autocast region (a bf16-mixed trainer's validation): SSIM's local
variances E[x^2] - E[x]^2 of values near 255 cancel to noise in bfloat16.
"""

from __future__ import annotations

from typing import cast

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


def ssim(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-image SSIM, [B], of [B, 3, H, W] images (uint8 or [-1, 1] floats), mean over channels."""
    from torchmetrics.functional.image import structural_similarity_index_measure

    with torch.autocast(pred.device.type, enabled=False):
        p, t = _prepare(pred), _prepare(target)
        out = structural_similarity_index_measure(
            p, t, gaussian_kernel=True, kernel_size=11, sigma=1.5, data_range=255.0, reduction="none"
        )
    return cast(torch.Tensor, out)  # a tuple only with return_full_image=True


def ssim_unquantised(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-image SSIM, [B], of [-1, 1] float images as :func:`ssim` computes it but without the 8-bit
    rounding, so it has gradients (a training loss). Equal to :func:`ssim` on images that are already 8-bit
    values."""
    from torchmetrics.functional.image import structural_similarity_index_measure

    with torch.autocast(pred.device.type, enabled=False):
        p, t = (pred.float() + 1) / 2, (target.float() + 1) / 2  # SSIM is unchanged by scaling x and its range
        out = structural_similarity_index_measure(
            p, t, gaussian_kernel=True, kernel_size=11, sigma=1.5, data_range=1.0, reduction="none"
        )
    return cast(torch.Tensor, out)


def mse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-image MSE on the 0-255 scale, [B], of [B, 3, H, W] images (uint8 or [-1, 1] floats)."""
    with torch.autocast(pred.device.type, enabled=False):
        p, t = _prepare(pred), _prepare(target)
        return ((p - t) ** 2).flatten(1).mean(1)
