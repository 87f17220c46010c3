"""The report's figures, drawn with PIL (no plotting library needed).

- ``example_grid``: the paper's Fig. 3 / 4 layout, one row per touch, columns RGB | depth | generated | target |
  thresholded difference. The target is the pair's touch: the simulator's image, or the recorded frame of a
  captured object (``objects=captured``).
- ``bar_plot``: SSIM per object, one bar per method (with standard-error whiskers).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from tnf.eval.aggregate import Stat
from tnf.metrics import to_uint8_scale

COLUMNS = ("RGB", "depth", "generated", "target", "difference")
# Colour-blind-safe palette (Okabe-Ito); BG is drawn grey.
PALETTE = [(0, 114, 178), (230, 159, 0), (0, 158, 115), (204, 121, 167), (86, 180, 233), (213, 94, 0), (240, 228, 66)]
GREY = (150, 150, 150)


def _font() -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    return ImageFont.load_default()


def _hwc(x: torch.Tensor) -> np.ndarray:
    """[C, H, W] in [-1, 1] (C = 1 or 3) -> uint8 [H, W, 3]."""
    u = to_uint8_scale(x[None])[0].clamp(0, 255).byte()
    if u.shape[0] == 1:
        u = u.expand(3, -1, -1)
    return u.permute(1, 2, 0).numpy()


def threshold_difference(generated: torch.Tensor, target: torch.Tensor, threshold: float) -> np.ndarray:
    """|generated - target| averaged over channels on the 0-255 scale, zero below ``threshold``; uint8 [H, W, 3].

    Inputs ``[3, H, W]`` in [-1, 1]. Thresholding removes the low-level noise so the indentation mismatch shows.
    """
    d = (to_uint8_scale(generated[None]) - to_uint8_scale(target[None]))[0].abs().mean(0)
    d = torch.where(d >= threshold, d, torch.zeros_like(d)).clamp(0, 255).byte()
    return d[..., None].expand(-1, -1, 3).numpy()


def example_grid(
    examples: Mapping[str, torch.Tensor],
    threshold: float = 20.0,
    labels: Sequence[str] | None = None,
    cell: int = 128,
) -> Image.Image:
    """One row per example: RGB | depth | generated | target | thresholded difference.

    ``examples``: rgb [N,3,H,W], depth [N,1,H,W], generated [N,3,H,W], target [N,3,H,W] in [-1, 1]; ``labels``
    (one per row, e.g. object names) are written at the left. ``threshold`` is on the 0-255 scale.
    """
    n = len(examples["target"])
    left = 90 if labels else 0
    top, pad = 18, 4
    img = Image.new("RGB", (left + len(COLUMNS) * (cell + pad) + pad, top + n * (cell + pad) + pad), "white")
    draw = ImageDraw.Draw(img)
    font = _font()
    for c, name in enumerate(COLUMNS):
        draw.text((left + pad + c * (cell + pad) + 4, 3), name, fill="black", font=font)
    for r in range(n):
        tiles = [
            _hwc(examples["rgb"][r]),
            _hwc(examples["depth"][r]),
            _hwc(examples["generated"][r]),
            _hwc(examples["target"][r]),
            threshold_difference(examples["generated"][r], examples["target"][r], threshold),
        ]
        y = top + pad + r * (cell + pad)
        for c, t in enumerate(tiles):
            tile = Image.fromarray(np.ascontiguousarray(t)).resize((cell, cell), Image.Resampling.NEAREST)
            img.paste(tile, (left + pad + c * (cell + pad), y))
        if labels:
            draw.text((4, y + cell // 2 - 6), str(labels[r])[:14], fill="black", font=font)
    return img


def bar_plot(
    series: Mapping[str, Mapping[str, Stat]],
    title: str,
    y_range: tuple[float, float] = (0.0, 1.0),
    y_label: str = "SSIM",
) -> Image.Image:
    """Grouped bars: x = category (object), one bar per series (method), whiskers = standard error.

    ``series``: method -> object -> Stat. Categories are the union of objects, sorted.
    """
    cats = sorted({c for s in series.values() for c in s})
    names = list(series)
    bar_w, gap = 10, 14
    group_w = max(1, len(names)) * bar_w + gap
    left, right, top, bottom = 56, 20, 30, 110
    plot_h = 260
    width = max(360, left + right + len(cats) * group_w)
    legend_h = 16 * len(names) + 8
    img = Image.new("RGB", (width, top + plot_h + bottom + legend_h), "white")
    d = ImageDraw.Draw(img)
    font = _font()
    lo, hi = y_range

    def y_of(v: float) -> float:
        return top + plot_h * (1 - (min(max(v, lo), hi) - lo) / (hi - lo))

    d.text((left, 8), title, fill="black", font=font)
    for k in range(6):  # horizontal grid and tick labels
        v = lo + (hi - lo) * k / 5
        y = y_of(v)
        d.line([(left, y), (width - right, y)], fill=(225, 225, 225))
        d.text((4, y - 6), f"{v:.2f}", fill="black", font=font)
    d.line([(left, top), (left, top + plot_h), (width - right, top + plot_h)], fill="black")
    d.text((4, top - 22), y_label, fill="black", font=font)
    colours = {n: (GREY if n == "BG" else PALETTE[i % len(PALETTE)]) for i, n in enumerate(names)}
    for ci, cat in enumerate(cats):
        x0 = left + gap // 2 + ci * group_w
        for si, name in enumerate(names):
            st = series[name].get(cat)
            if st is None:
                continue
            x = x0 + si * bar_w
            d.rectangle([x, y_of(st.mean), x + bar_w - 2, top + plot_h], fill=colours[name])
            if st.se > 0:
                xm = x + (bar_w - 2) / 2
                d.line([(xm, y_of(st.mean - st.se)), (xm, y_of(st.mean + st.se))], fill="black")
        # Object names run downwards below the axis.
        label = Image.new("RGB", (bottom - 8, 12), "white")
        ImageDraw.Draw(label).text((0, 0), cat[:16], fill="black", font=font)
        label = label.rotate(90, expand=True)
        img.paste(label, (int(x0 + group_w / 2 - 12), top + plot_h + 4))
    for si, name in enumerate(names):
        y = top + plot_h + bottom + 4 + 16 * si
        d.rectangle([left, y, left + 12, y + 10], fill=colours[name])
        d.text((left + 18, y - 1), name, fill="black", font=font)
    return img


def axis_ticks(lo: float, hi: float, most: int = 6, whole: bool = False) -> list[tuple[float, str]]:
    """At most ``most`` round tick values in [lo, hi] (steps of 1, 2 or 5 times a power of ten), each with its
    label, each where it lies; ``whole``: whole numbers only (an axis of epochs)."""
    if most < 4:
        raise ValueError(f"axis_ticks needs most >= 4 (a narrower choice can leave a span without a tick), got {most}")
    if hi <= lo:
        return [(lo, f"{lo:g}")]
    # A power of ten at most the narrowest allowed step; 1, 2, 5 or 10 times it gives at most ``most`` ticks.
    step = 10.0 ** math.floor(math.log10((hi - lo) / (most - 1)))
    step = next(m * step for m in (1, 2, 5, 10) if (hi - lo) / (m * step) <= most - 1 + 1e-9)
    step = max(step, 1.0) if whole else step
    decimals = max(0, -math.floor(math.log10(step) + 1e-9))
    first = math.ceil(lo / step - 1e-9)
    ticks = []
    for k in range(first, first + most + 1):
        v = k * step
        if v > hi + step * 1e-9:
            break
        ticks.append((v, f"{v:.{decimals}f}"))
    return ticks


def line_plot(
    lines: Mapping[str, Sequence[tuple[float, float]]],
    colour_of: Mapping[str, str],
    title: str,
    y_label: str = "SSIM",
    x_label: str = "epoch",
) -> Image.Image:
    """Lines of (x, y) points, one per key of ``lines`` (e.g. a run); ``colour_of`` maps each key to its group
    (e.g. the method), which sets its colour and the legend. Axes span the points' range."""
    pts = [p for ps in lines.values() for p in ps]
    if not pts:
        raise ValueError("line_plot needs at least one point")
    groups = list(dict.fromkeys(colour_of[k] for k in lines))
    colours = {g: PALETTE[i % len(PALETTE)] for i, g in enumerate(groups)}
    left, right, top, bottom, plot_w, plot_h = 56, 20, 30, 36, 480, 260
    legend_h = 16 * len(groups) + 8
    img = Image.new("RGB", (left + plot_w + right, top + plot_h + bottom + legend_h), "white")
    d = ImageDraw.Draw(img)
    font = _font()
    x_lo, x_hi = min(p[0] for p in pts), max(p[0] for p in pts)
    y_lo, y_hi = min(p[1] for p in pts), max(p[1] for p in pts)
    x_hi, y_hi = (x_hi if x_hi > x_lo else x_lo + 1), (y_hi if y_hi > y_lo else y_lo + 1e-3)
    pad = (y_hi - y_lo) * 0.05
    y_lo, y_hi = y_lo - pad, y_hi + pad

    def xy(x: float, y: float) -> tuple[float, float]:
        return left + plot_w * (x - x_lo) / (x_hi - x_lo), top + plot_h * (1 - (y - y_lo) / (y_hi - y_lo))

    d.text((left, 8), title, fill="black", font=font)
    for v, label in axis_ticks(y_lo, y_hi, most=8):
        y = xy(x_lo, v)[1]
        d.line([(left, y), (left + plot_w, y)], fill=(225, 225, 225))
        d.text((4, y - 6), label, fill="black", font=font)
    for v, label in axis_ticks(x_lo, x_hi, whole=all(float(p[0]).is_integer() for p in pts)):
        x = xy(v, y_lo)[0]
        d.line([(x, top + plot_h), (x, top + plot_h + 3)], fill="black")
        d.text((x - 3 * len(label), top + plot_h + 4), label, fill="black", font=font)
    d.line([(left, top), (left, top + plot_h), (left + plot_w, top + plot_h)], fill="black")
    d.text((4, top - 22), y_label, fill="black", font=font)
    d.text((left + plot_w - 40, top + plot_h + 18), x_label, fill="black", font=font)
    for key, ps in lines.items():
        c = colours[colour_of[key]]
        coords = [xy(x, y) for x, y in sorted(ps)]
        if len(coords) > 1:
            d.line(coords, fill=c, width=2)
        for x, y in coords:
            d.ellipse([x - 2, y - 2, x + 2, y + 2], fill=c)
    for gi, g in enumerate(groups):
        y = top + plot_h + bottom + 4 + 16 * gi
        d.rectangle([left, y, left + 12, y + 10], fill=colours[g])
        d.text((left + 18, y - 1), g, fill="black", font=font)
    return img
