"""Preprocessing of rendered RGB-D and tactile images into the 128 x 128 arrays a paired dataset stores.

The paper's preprocessing: centre-crop the rendered RGB-D image around the centre camera ray (where the
sensor sits), normalise the depth, and scale every image to 128 x 128.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
import torch
import torch.nn.functional as F

from tnf.errors import TnfError

SIZE = 128
"""Side of every stored image, in pixels (the paper's cGAN input and output size)."""

DepthNorm = Literal["contact", "center", "minmax"]


def preprocess_rgbd(
    rgb: torch.Tensor,
    depth: torch.Tensor,
    opacity: torch.Tensor | None,
    crop_px: int,
    depth_norm: DepthNorm = "center",
    out: int = SIZE,
    depth_window: float = 0.04,
    center: tuple[float, float] | None = None,
    min_opacity: float = 0.5,
    contact: torch.Tensor | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Crop around the centre ray, normalise depth, resize.

    Args:
        rgb: [B, H, W, 3] float in [0, 1].
        depth: [B, H, W] z-depth in metres, 0 where no surface was hit.
        opacity: [B, H, W] in [0, 1] (accumulated opacity), or None to treat depth > 0 as a hit.
        crop_px: side of the square crop in pixels, centred on the centre ray; must fit in the image.
        depth_norm: ``contact``: ``0.5 + (d - contact) / depth_window`` clipped to [0, 1], so the surface
            point the gel reaches first is 0.5 and a fixed window of ``depth_window`` metres spans [0, 1];
            ``center``: the same with the depth of the centre pixel (the nearest hit in the crop when the
            centre ray misses) in place of ``contact``;
            ``minmax``: ``(d - min) / (max - min)`` over the hit pixels of the crop.
            In both, pixels with no surface (opacity < ``min_opacity`` or depth 0) are 1 (far).
        out: output side in pixels.
        depth_window: metres of depth mapped onto [0, 1] by the ``contact`` and ``center`` normalisations.
        center: pixel coordinates ``(cx, cy)`` of the centre ray; default the image centre.
        min_opacity: opacity below which a pixel counts as empty.
        contact: [B] metres, the depth that ``contact`` normalisation maps to 0.5 (see ``contact_depth``).

    Returns:
        ``(rgb uint8 [B, out, out, 3], depth float16 [B, out, out] in [0, 1])`` as NumPy arrays.
    """
    if rgb.ndim != 4 or rgb.shape[-1] != 3:
        raise ValueError(f"rgb must be [B, H, W, 3], got {tuple(rgb.shape)}")
    b, h, w, _ = rgb.shape
    if tuple(depth.shape) != (b, h, w):
        raise ValueError(f"depth must be [B, H, W] = {(b, h, w)}, got {tuple(depth.shape)}")
    if depth_norm not in ("contact", "center", "minmax"):
        raise TnfError(f"depth_norm must be 'contact', 'center' or 'minmax', got {depth_norm!r}")
    if depth_norm == "contact" and (contact is None or tuple(contact.shape) != (b,)):
        raise ValueError(f"depth_norm='contact' needs contact depths of shape [{b}]")
    if depth_window <= 0:
        raise TnfError(f"depth_window must be > 0 metres, got {depth_window}")
    x0, y0 = crop_origin(w, h, crop_px, center)

    rgb = rgb[:, y0 : y0 + crop_px, x0 : x0 + crop_px].float()
    depth = depth[:, y0 : y0 + crop_px, x0 : x0 + crop_px].float()
    hit = depth > 0
    if opacity is not None:
        hit &= opacity[:, y0 : y0 + crop_px, x0 : x0 + crop_px] >= min_opacity

    nd = _normalise_depth(depth, hit, depth_norm, depth_window, contact)
    rgb_o = resize(rgb.permute(0, 3, 1, 2), out)
    nd_o = resize(nd[:, None], out)[:, 0]
    rgb8 = (rgb_o.clamp(0, 1) * 255).round().to(torch.uint8).permute(0, 2, 3, 1)
    return rgb8.cpu().numpy(), nd_o.clamp(0, 1).to(torch.float16).cpu().numpy()


def crop_origin(width: int, height: int, crop_px: int, center: tuple[float, float] | None = None) -> tuple[int, int]:
    """Top-left pixel of a ``crop_px`` square centred on ``center`` (default the image centre).

    Raises TnfError when the crop does not fit in the image.
    """
    if crop_px < 1:
        raise TnfError(f"crop must be at least 1 pixel, got {crop_px}")
    if crop_px > min(width, height):
        raise TnfError(f"crop of {crop_px} px is larger than the {width}x{height} image; use a smaller pair.crop_px")
    cx, cy = center if center is not None else (width / 2, height / 2)
    # The crop's centre (x0 + crop/2) sits on the centre ray; rounding keeps it within half a pixel.
    x0 = min(max(int(round(cx - crop_px / 2)), 0), width - crop_px)
    y0 = min(max(int(round(cy - crop_px / 2)), 0), height - crop_px)
    return x0, y0


def _normalise_depth(
    depth: torch.Tensor, hit: torch.Tensor, mode: str, window: float, contact: torch.Tensor | None = None
) -> torch.Tensor:
    """[B, S, S] metres -> [B, S, S] in [0, 1]; empty pixels 1."""
    b, s, _ = depth.shape
    big = torch.finfo(depth.dtype).max
    if mode == "contact":
        assert contact is not None
        nd = 0.5 + (depth - contact.to(depth)[:, None, None]) / window
    elif mode == "center":
        c = s // 2
        # The centre "pixel" of an even crop is the 2x2 block around the ray; use its nearest hit.
        lo, hi = (c - 1, c + 1) if s % 2 == 0 else (c, c + 1)
        block = torch.where(hit[:, lo:hi, lo:hi], depth[:, lo:hi, lo:hi], big).flatten(1).amin(1)
        nearest = torch.where(hit, depth, big).flatten(1).amin(1)
        ref = torch.where(block < big, block, nearest)
        nd = 0.5 + (depth - ref[:, None, None]) / window
    else:
        dmin = torch.where(hit, depth, big).flatten(1).amin(1)
        dmax = torch.where(hit, depth, -big).flatten(1).amax(1)
        span = (dmax - dmin).clamp_min(1e-9)
        nd = (depth - dmin[:, None, None]) / span[:, None, None]
    return torch.where(hit, nd.clamp(0, 1), torch.ones_like(nd))


def resize(x: torch.Tensor, out: int) -> torch.Tensor:
    """[B, C, H, W] float -> [B, C, out, out], bilinear with antialiasing when shrinking."""
    if x.shape[-2:] == (out, out):
        return x
    return F.interpolate(x, size=(out, out), mode="bilinear", align_corners=False, antialias=True)


def resize_uint8(images: np.ndarray | torch.Tensor, out: int = SIZE) -> np.ndarray:
    """[B, H, W, 3] (or [H, W, 3]) uint8 images -> uint8 [B, out, out, 3] (aspect ratio not kept, as the paper)."""
    a = np.asarray(images)
    t = torch.from_numpy(a if a.flags.writeable else a.copy())
    single = t.ndim == 3
    if single:
        t = t[None]
    if t.shape[-1] == 4:  # RGBA -> RGB
        t = t[..., :3]
    y = resize(t.permute(0, 3, 1, 2).float(), out).round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1)
    arr = y.numpy()
    return arr[0] if single else arr


def gel_size_m(sensor: Any) -> tuple[float, float]:
    """The gel's (width, height) in metres, read from a sensor object or its config.

    Accepts a ``gel_size`` attribute (metres) or config fields ``gel_width``/``gel_height`` (metres) or
    ``gel_width_mm``/``gel_height_mm``; a dome gel may give ``gel_radius`` (metres).
    """
    for obj in (sensor, getattr(sensor, "cfg", None), getattr(sensor, "config", None)):
        if obj is None:
            continue
        size = getattr(obj, "gel_size", None)
        if size is not None:
            w, h = (float(v) for v in size)
            return w, h
        if getattr(obj, "gel_width", None) is not None and getattr(obj, "gel_height", None) is not None:
            return float(obj.gel_width), float(obj.gel_height)
        if getattr(obj, "gel_width_mm", None) is not None and getattr(obj, "gel_height_mm", None) is not None:
            return float(obj.gel_width_mm) / 1000, float(obj.gel_height_mm) / 1000
        r = getattr(obj, "gel_radius", None)
        if r is not None:
            return 2 * float(r), 2 * float(r)
    raise TnfError(f"sensor {type(sensor).__name__} does not state its gel size; set pair.crop_px explicitly")


def footprint_px(
    focal: tuple[float, float], gel_size: tuple[float, float], distance: float, margin: float = 1.0
) -> float:
    """Side in pixels of a camera with focal lengths ``focal`` that covers the gel's footprint (its larger side
    times ``margin``) on a surface ``distance`` metres away."""
    if distance <= 0:
        raise TnfError(f"distance to the surface must be > 0 metres, got {distance}")
    return margin * max(focal[0] * gel_size[0], focal[1] * gel_size[1]) / distance


def crop_for_sensor(
    sensor: Any, intrinsics: Sequence[float] | torch.Tensor, distance: float = 0.05, margin: float = 1.0
) -> int:
    """Crop side in whole pixels that covers the sensor's gel footprint seen from ``distance`` metres.

    Args:
        sensor: a sensor (or its config) stating its gel size (see ``gel_size_m``).
        intrinsics: ``(fx, fy, cx, cy)`` of the render camera in pixels.
        distance: metres from the camera to the touched surface along the centre ray.
        margin: factor applied to the footprint (1 = exactly the gel's larger side).
    """
    focal = (float(intrinsics[0]), float(intrinsics[1]))
    return max(1, int(math.ceil(footprint_px(focal, gel_size_m(sensor), distance, margin))))


def contact_depth(depth: torch.Tensor, intrinsics: torch.Tensor, gel_size: tuple[float, float]) -> torch.Tensor:
    """Depth along the view axis of the nearest surface inside the gel's footprint, per view: where the gel
    first meets the object as the sensor advances along its axis.

    Args:
        depth: [B, H, W] z-depth in metres, 0 where no surface was hit.
        intrinsics: [B, 4] or [4] ``(fx, fy, cx, cy)`` in pixels of the camera that rendered ``depth``.
        gel_size: the gel's (width, height) in metres, along the image's x and y.

    Returns:
        [B] metres; NaN where no surface lies inside the footprint.
    """
    b, h, w = depth.shape
    k = intrinsics.to(depth.device, torch.float32).reshape(-1, 4).expand(b, 4)
    u = torch.arange(w, device=depth.device, dtype=torch.float32) + 0.5
    v = torch.arange(h, device=depth.device, dtype=torch.float32) + 0.5
    # Lateral offset of each pixel's surface point from the axis, in metres: (u - cx) / fx * z.
    x = (u[None, None, :] - k[:, 2, None, None]) / k[:, 0, None, None] * depth
    y = (v[None, :, None] - k[:, 3, None, None]) / k[:, 1, None, None] * depth
    inside = (depth > 0) & (x.abs() <= gel_size[0] / 2) & (y.abs() <= gel_size[1] / 2)
    nearest = torch.where(inside, depth.float(), torch.full_like(depth, math.inf, dtype=torch.float32))
    nearest = nearest.flatten(1).amin(1)
    return torch.where(torch.isfinite(nearest), nearest, torch.full_like(nearest, math.nan))
