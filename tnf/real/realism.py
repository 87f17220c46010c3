"""How close simulated presses come to real frames: SSIM and MSE on the whole frame and on the contact region.

The contact region of a press is the disk of ``region_scale`` times its contact radius around its centre: the
background alone scores high on the whole frame, so the region is the figure that counts. SSIM is tnf's metric
(:func:`tnf.metrics.ssim_map`: 11 px Gaussian window, sigma 1.5, 8-bit range) at the sensor's own size,
its per-pixel map averaged over the frame or the region; MSE is on the 0-255 scale.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from tnf.errors import TnfError
from tnf.real.presses import PressSet, SensorPresses, at_sensor_size, disk_masks, sphere_gaps
from tnf.registry import SIMULATORS
from tnf.sensors.base import Sensor

METRICS = ("ssim_frame", "mse_frame", "ssim_region", "mse_region")


def score(pred: np.ndarray, real: np.ndarray, region: np.ndarray) -> dict[str, list[float]]:
    """Per-frame realism of ``pred`` against ``real`` (both ``[N, H, W, 3]`` uint8), ``region`` ``[N, H, W]`` bool.

    Returns ``{metric: [N] floats}`` for each of ``METRICS``.
    """
    import torch

    from tnf.metrics import ssim_map  # lazy: imports torch

    p = torch.from_numpy(np.ascontiguousarray(pred)).permute(0, 3, 1, 2)
    t = torch.from_numpy(np.ascontiguousarray(real)).permute(0, 3, 1, 2)
    smap = ssim_map(p, t).numpy()
    sq = ((pred.astype(np.float64) - real.astype(np.float64)) ** 2).mean(-1)
    out: dict[str, list[float]] = {m: [] for m in METRICS}
    for i in range(len(pred)):
        m = region[i]
        out["ssim_frame"].append(float(smap[i].mean()))
        out["mse_frame"].append(float(sq[i].mean()))
        out["ssim_region"].append(float(smap[i][m].mean()))
        out["mse_region"].append(float(sq[i][m].mean()))
    return out


def regions(sp: SensorPresses, region_scale: float) -> np.ndarray:
    """``[N, H, W]`` bool contact regions of the presses (``region_scale`` times each contact radius)."""
    return disk_masks(sp.background.shape[:2], sp.centers, region_scale * sp.radii)


def render(
    sensor: Sensor, simulator: Mapping[str, Any], sp: SensorPresses, radius_m: float, depth_scale: float = 1.0
) -> tuple[np.ndarray, float]:
    """Simulated frames ``[N, H, W, 3]`` uint8 of the presses (without pixel noise: noise is independent of the
    real frame's and would only add to the error), and the simulator's seconds per frame."""
    import time

    quiet = type(sensor)(dataclasses.replace(sensor.cfg, noise_std=0.0))
    if sensor.calibration is not None:
        quiet = quiet.calibrated(dataclasses.replace(sensor.calibration, noise_std=0.0), str(sensor.cfg.calibration))
    sim = SIMULATORS.build(dict(simulator), sensor=quiet, device="cpu")
    gaps = sphere_gaps(quiet, sp.centers, radius_m)
    sim.press_heights(gaps[:1], penetration=sp.depths[:1] * depth_scale)  # compile and warm up
    t0 = time.perf_counter()
    out = sim.press_heights(gaps, penetration=sp.depths * depth_scale)
    return out.images, (time.perf_counter() - t0) / len(gaps)


def render_native(
    sensor: Sensor,
    simulator: Mapping[str, Any],
    presses: PressSet,
    indices: Sequence[int],
    depth_scale: float = 1.0,
) -> tuple[np.ndarray, float]:
    """The calibrated ``sensor``'s presses rendered at the recording's own size (``presses.width x height``):
    ``[N, H, W, 3]`` uint8 and the seconds per frame. The calibration is :meth:`Calibration.resized` to the
    recording's background; the sensor keeps its field of view, so its pixels are the recording's."""
    cal = sensor.calibration
    if cal is None:
        raise TnfError(f"sensor {sensor.name!r} has no calibration to render at the recording's size")
    big = type(sensor)(
        dataclasses.replace(sensor.cfg, width=presses.width, height=presses.height, calibration=None, noise_std=0.0)
    )
    big = big.calibrated(cal.resized(presses.background()), f"{sensor.cfg.calibration} at the recording's size")
    sp = at_sensor_size(presses, big, indices)
    return render(big, simulator, sp, presses.radius_mm * 1e-3, depth_scale)


def native_score(images: np.ndarray, presses: PressSet, indices: Sequence[int], scale: float = 4.0) -> dict:
    """:func:`crop_score` of ``images`` ``[N, h, w, 3]`` uint8 (upsampled bilinearly to the recording's size when
    smaller) against the recording's frames ``indices``, at the annotated centres and contact radii."""
    real = np.stack([presses.frame(i) for i in indices])
    centers = np.array([presses.presses[i].center for i in indices], dtype=float)
    radii = np.array([presses.contact_radius_px(i) for i in indices], dtype=float)
    return crop_score(upsample(images, presses.width, presses.height), real, centers, radii, scale)


def grid(
    real: np.ndarray,
    simulated: Mapping[str, np.ndarray],
    centers: np.ndarray,
    path: str | Path,
    crop: int = 96,
    gain: float = 3.0,
    zoom: int = 2,
    diffs: bool = True,
) -> None:
    """Save a PNG: one row per press, columns real | each simulator | (with ``diffs``) each simulator's
    |difference| x ``gain``, cropped to ``crop`` pixels around the contact and enlarged ``zoom`` times."""
    from PIL import Image, ImageDraw

    names = list(simulated)
    h, w = real.shape[1:3]
    half = crop // 2
    tiles: list[list[np.ndarray]] = []
    for i in range(len(real)):
        c = int(np.clip(round(centers[i][0]), half, w - half))
        r = int(np.clip(round(centers[i][1]), half, h - half))
        box = (slice(r - half, r + half), slice(c - half, c + half))
        row = [real[i][box]] + [simulated[n][i][box] for n in names]
        for n in names if diffs else []:
            d = np.abs(simulated[n][i][box].astype(np.float32) - real[i][box].astype(np.float32))
            row.append(np.clip(d * gain, 0, 255).astype(np.uint8))
        tiles.append(row)
    labels = ["real"] + names + ([f"|{n} - real| x{gain:g}" for n in names] if diffs else [])
    cell, pad, top = zoom * crop, 4, 18
    img = Image.new("RGB", (len(labels) * (cell + pad), top + len(tiles) * (cell + pad)), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    for k, lab in enumerate(labels):
        draw.text((k * (cell + pad) + 2, 2), lab, fill=(0, 0, 0))
    for i, row in enumerate(tiles):
        for k, t in enumerate(row):
            tile = Image.fromarray(np.ascontiguousarray(t)).resize((cell, cell), Image.Resampling.NEAREST)
            img.paste(tile, (k * (cell + pad), top + i * (cell + pad)))
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    img.save(path)


CROP_METRICS = ("ssim_crop", "mse_crop", "sharpness")


def ssim_uniform(a: np.ndarray, b: np.ndarray) -> float:
    """Mean SSIM of two ``[H, W, 3]`` uint8 images with scikit-image's defaults.

    A 7 x 7 uniform window, sample covariances, K1 = 0.01, K2 = 0.03, data range 255, borders of 3 pixels left
    out of the mean, channels averaged: ``skimage.metrics.structural_similarity(a, b, channel_axis=-1)``.
    """
    from scipy.ndimage import uniform_filter

    win, pad = 7, 3
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    norm = win * win / (win * win - 1.0)
    out = []
    for ch in range(a.shape[-1]):
        x, y = a[..., ch].astype(np.float64), b[..., ch].astype(np.float64)
        mx, my = uniform_filter(x, win), uniform_filter(y, win)
        vx = norm * (uniform_filter(x * x, win) - mx * mx)
        vy = norm * (uniform_filter(y * y, win) - my * my)
        cxy = norm * (uniform_filter(x * y, win) - mx * my)
        s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
        out.append(s[pad:-pad, pad:-pad].mean())
    return float(np.mean(out))


def sharpness(img: np.ndarray) -> float:
    """Mean Sobel gradient magnitude of ``[H, W, 3]`` uint8 (8-bit units per pixel, channels averaged)."""
    from scipy.ndimage import sobel

    f = img.astype(np.float64)
    return float(np.hypot(sobel(f, axis=0), sobel(f, axis=1)).mean())


def crop_boxes(shape: tuple[int, int], centers: np.ndarray, radii: np.ndarray, scale: float = 4.0) -> list[tuple]:
    """Square crops of side ``scale`` x each contact radius around each centre ``(column, row)``, clipped to
    ``shape`` ``(H, W)``: ``[(rows slice, cols slice)]``."""
    h, w = shape
    boxes = []
    for (col, row), r in zip(np.asarray(centers, float).reshape(-1, 2), np.asarray(radii, float).reshape(-1)):
        half = max(4, int(round(scale * r / 2)))
        r0, c0 = int(round(row)) - half, int(round(col)) - half
        boxes.append((slice(max(0, r0), min(h, r0 + 2 * half)), slice(max(0, c0), min(w, c0 + 2 * half))))
    return boxes


def crop_score(
    pred: np.ndarray, real: np.ndarray, centers: np.ndarray, radii: np.ndarray, scale: float = 4.0
) -> dict[str, list[float]]:
    """Realism on a square crop of side ``scale`` x the contact radius around each contact, per press.

    ``pred`` and ``real`` are ``[N, H, W, 3]`` uint8 at one size (the recording's own, for the native figure);
    ``centers`` ``[N, 2]`` ``(column, row)`` and ``radii`` ``[N]`` are pixels at that size. Returns
    ``{"ssim_crop", "mse_crop", "sharpness"}`` -> ``[N]``: SSIM as :func:`ssim_uniform`, MSE on the 0-255
    scale, and sharpness as :func:`sharpness` of ``pred`` over that of ``real``.
    """
    if pred.shape != real.shape:
        raise ValueError(f"pred {pred.shape} and real {real.shape} differ")
    out: dict[str, list[float]] = {m: [] for m in CROP_METRICS}
    for i, box in enumerate(crop_boxes(real.shape[1:3], centers, radii, scale)):
        p, t = pred[i][box], real[i][box]
        out["ssim_crop"].append(ssim_uniform(p, t))
        out["mse_crop"].append(float(((p.astype(np.float64) - t) ** 2).mean()))
        out["sharpness"].append(sharpness(p) / max(sharpness(t), 1e-9))
    return out


def upsample(images: np.ndarray, width: int, height: int) -> np.ndarray:
    """``[N, h, w, 3]`` uint8 resized to ``width x height`` with PIL's bilinear filter."""
    from PIL import Image

    if images.shape[1:3] == (height, width):
        return images
    return np.stack(
        [
            np.asarray(Image.fromarray(np.ascontiguousarray(f)).resize((width, height), Image.Resampling.BILINEAR))
            for f in images
        ]
    )
