"""An analytic test object: a coloured sphere rendered exactly in NumPy, written as a capture dataset.

Used by tests and the scene benchmark where no captured object is at hand. The dataset has the layout of
``tnf capture``: ``transforms.json`` / ``transforms_test.json`` (instant-ngp format, OpenGL c2w), RGBA PNGs
and float32 z-depth ``.npy`` files (0 where no object).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from tnf.cameras import look_at


def sphere_poses(n: int, distance: float, offset: float = 0.0) -> np.ndarray:
    """[n, 4, 4] cameras on a Fibonacci sphere of radius ``distance`` (metres) looking at the origin."""
    i = np.arange(n) + 0.5
    polar = np.arccos(1 - 2 * i / n)
    azim = math.pi * (1 + 5**0.5) * i + 2 * math.pi * offset
    eyes = distance * np.stack([np.cos(azim) * np.sin(polar), np.sin(azim) * np.sin(polar), np.cos(polar)], -1)
    return np.stack([look_at(e) for e in eyes])


def sphere_colour(p: np.ndarray, radius: float) -> np.ndarray:
    """Albedo of the test sphere at surface points [..., 3]: smooth colour bands, in [0, 1]."""
    q = p / radius
    return np.clip(
        np.stack([0.5 + 0.4 * q[..., 0], 0.5 + 0.4 * np.sin(3 * q[..., 1]), 0.5 + 0.4 * q[..., 2] ** 2], -1), 0, 1
    )


def render_sphere(
    c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float, w: int, h: int, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Exact RGBA [H, W, 4] (float, alpha 0/1) and z-depth [H, W] (metres, 0 off the object) of the sphere."""
    v, u = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    d_cam = np.stack([(u - cx) / fx, -(v - cy) / fy, -np.ones_like(u)], -1)
    d = d_cam @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = c2w[:3, 3]
    b = d @ o
    disc = b**2 - (o @ o - radius**2)
    hit = disc > 0
    t = -b - np.sqrt(np.where(hit, disc, 0))
    p = o + t[..., None] * d
    rgba = np.zeros((h, w, 4))
    rgba[..., :3] = np.where(hit[..., None], sphere_colour(p, radius), 0)
    rgba[..., 3] = hit
    z = np.where(hit, t * (d @ -c2w[:3, 2]), 0.0)
    return rgba, z.astype(np.float32)


def write_sphere_dataset(
    folder: str | os.PathLike[str],
    n_train: int = 12,
    n_test: int = 3,
    size: int = 32,
    radius: float = 0.05,
    distance: float = 0.2,
    fov_deg: float = 50.0,
) -> Path:
    """Write a capture-format dataset of the analytic sphere (radius metres) to ``folder``; returns it."""
    from PIL import Image

    folder = Path(folder)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(parents=True, exist_ok=True)
    angle = math.radians(fov_deg)
    f = 0.5 * size / math.tan(0.5 * angle)
    for split, n, offset in (("train", n_train, 0.0), ("test", n_test, 0.37)):
        frames = []
        for k, c2w in enumerate(sphere_poses(n, distance, offset)):
            rgba, z = render_sphere(c2w, f, f, size / 2, size / 2, size, size, radius)
            img = f"images/{split}_{k:03d}.png"
            dep = f"depth/{split}_{k:03d}.npy"
            Image.fromarray((rgba * 255).round().astype(np.uint8), "RGBA").save(folder / img)
            np.save(folder / dep, z)
            frames.append({"file_path": img, "depth_file_path": dep, "transform_matrix": c2w.tolist()})
        meta = {
            "camera_angle_x": angle,
            "fl_x": f,
            "fl_y": f,
            "cx": size / 2,
            "cy": size / 2,
            "w": size,
            "h": size,
            "frames": frames,
        }
        name = "transforms.json" if split == "train" else "transforms_test.json"
        (folder / name).write_text(json.dumps(meta, indent=1))
    return folder
