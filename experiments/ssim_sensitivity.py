"""What each kind of error costs in SSIM and MSE, measured on simulated touches with everything else exact.

    python experiments/ssim_sensitivity.py tnf-data/touch/digit/builtin [--objects jar mug box]

Every row builds a prediction from the true tactile image T and the sensor's background B (imprint T - B):
the background alone (the BG row of the reports), a blurred or shifted imprint, a weaker or stronger imprint,
and the imprint scaled about the image centre by each touch's start-to-contact distance over the median, which
is what one fixed crop for every touch did to the RGB-D input (pair.crop_distance=fixed). Images are compared
as the reports compare them (tnf.metrics, 128 x 128).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from tnf import metrics
from tnf.data.render import TouchItem
from tnf.errors import TnfError


def gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    r = int(3 * sigma) + 1
    g = torch.exp(-(torch.arange(-r, r + 1.0) ** 2) / (2 * sigma * sigma))
    g = (g / g.sum()).to(x)
    c = x.shape[1]
    x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="replicate"), g.view(1, 1, 1, -1).repeat(c, 1, 1, 1), groups=c)
    return F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), g.view(1, 1, -1, 1).repeat(c, 1, 1, 1), groups=c)


def zoom(x: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Scale each image about its centre by ``scale`` [B] (zeros outside)."""
    theta = torch.zeros(len(x), 2, 3)
    theta[:, 0, 0] = theta[:, 1, 1] = 1 / scale
    grid = F.affine_grid(theta, list(x.shape), align_corners=False)
    return F.grid_sample(x, grid, align_corners=False, padding_mode="zeros")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("touch_root", type=Path, help="a folder of touch items, e.g. <data-root>/touch/digit/builtin")
    ap.add_argument("--objects", nargs="*", help="object folders to use (default: all)")
    args = ap.parse_args()

    folders = [args.touch_root / o for o in args.objects] if args.objects else sorted(args.touch_root.iterdir())
    folders = [f for f in folders if (f / "manifest.json").is_file()]
    if not folders:
        raise SystemExit(f"no touch items under {args.touch_root}")
    tactile, background, distance = [], [], []
    for f in folders:
        item = TouchItem.load(f)
        n = len(item.touches)
        tactile.append(item.tactile(list(range(n))))
        background.append(np.repeat(item.background()[None], n, 0))
        distance.append(item.contact_distances())
    t8 = torch.from_numpy(np.concatenate(tactile)).permute(0, 3, 1, 2).contiguous()
    t = t8.float()
    b = torch.from_numpy(np.concatenate(background)).permute(0, 3, 1, 2).float()
    d = np.concatenate(distance)
    imprint = t - b
    scale = torch.from_numpy(d / np.median(d)).float()
    print(f"{len(t)} touches of {len(folders)} objects; start-to-contact distance 5/50/95 %: "
          + " / ".join(f"{v:.3f}" for v in np.percentile(d, [5, 50, 95])) + " m")  # fmt: skip

    rows: list[tuple[str, Callable[[], torch.Tensor]]] = [
        ("BG (background only)", lambda: b),
        ("imprint blurred, sigma 1 px", lambda: b + gaussian_blur(imprint, 1.0)),
        ("imprint blurred, sigma 2 px", lambda: b + gaussian_blur(imprint, 2.0)),
        ("imprint shifted 1 px", lambda: b + torch.roll(imprint, 1, 3)),
        ("imprint shifted 2 px", lambda: b + torch.roll(imprint, 2, 3)),
        ("imprint x 0.5", lambda: b + 0.5 * imprint),
        ("imprint x 0.8", lambda: b + 0.8 * imprint),
        ("imprint x 1.2", lambda: b + 1.2 * imprint),
        ("imprint scaled by distance / median", lambda: b + zoom(imprint, scale)),
    ]
    print(f"{'prediction':<38} {'SSIM':>7} {'MSE':>7}")
    for name, make in rows:
        pred = make().round().clamp(0, 255).to(torch.uint8)
        s, m = metrics.ssim(pred, t8).mean(), metrics.mse(pred, t8).mean()
        print(f"{name:<38} {float(s):7.4f} {float(m):7.1f}")


if __name__ == "__main__":
    try:
        main()
    except TnfError as e:
        raise SystemExit(f"error: {e}") from None
