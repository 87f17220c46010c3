"""Multi-view RGB-D capture of an object, written in the instant-ngp / nerfstudio ``transforms.json`` format.

Cameras look at the origin from a sphere (``sphere``: Fibonacci-even) or from an azimuth/elevation range
(``hemisphere``), plus a separate set of held-out test views. Output folder of one object::

    transforms.json        training views: fl_x, fl_y, cx, cy, w, h, camera_angle_x, frames
    transforms_test.json   held-out views, same format
    images/train_000.png   RGBA, alpha = 255 where the object is
    depth/train_000.npy    float32 z-depth in metres, 0 where empty

Matrices are camera-to-world 4x4 in the OpenGL convention (camera looks along -z, +y up), metres; world +z
is the object's up.
"""

from __future__ import annotations

import json
import math
from concurrent.futures import Executor, Future
from pathlib import Path
from typing import Any

import numpy as np

from tnf.cameras import look_at
from tnf.capture.settings import CaptureConfig
from tnf.registry import from_dict

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


def capture_config(node: Any) -> CaptureConfig:
    """Validate ``cfg.capture`` (a Hydra node or dict) into a :class:`CaptureConfig`."""
    return from_dict(CaptureConfig, node or {}, where="capture")


# -- cameras ------------------------------------------------------------------------------------------------
def fibonacci_directions(n: int, rotation: np.ndarray | None = None) -> np.ndarray:
    """``n`` unit vectors spread evenly over the sphere (Fibonacci lattice), [n, 3]."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(np.clip(1 - z**2, 0, None))
    phi = GOLDEN_ANGLE * i
    d = np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)
    return d @ rotation.T if rotation is not None else d


def hemisphere_directions(n: int, cfg: CaptureConfig, rng: np.random.Generator) -> np.ndarray:
    """``n`` unit vectors uniform in area within the azimuth/elevation range of ``cfg``, [n, 3]."""
    lo, hi = np.sin(np.radians([cfg.min_elevation_deg, cfg.max_elevation_deg]))
    z = rng.uniform(lo, hi, n)
    az = np.radians(rng.uniform(cfg.min_azimuth_deg, cfg.max_azimuth_deg, n))
    r = np.sqrt(np.clip(1 - z**2, 0, None))
    return np.stack([r * np.cos(az), r * np.sin(az), z], 1)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


def camera_distance(radius: float, cfg: CaptureConfig) -> float:
    """Distance (metres) at which a bounding sphere of ``radius`` spans ``cfg.fill`` of the image width."""
    if cfg.distance is not None:
        return float(cfg.distance)
    # The sphere's silhouette half-angle asin(r/d) should be fill * fov/2.
    half = math.radians(cfg.fov_deg) / 2 * cfg.fill
    return radius / math.sin(half)


def intrinsics(cfg: CaptureConfig) -> tuple[float, float, float, float]:
    """Pinhole ``(fx, fy, cx, cy)`` in pixels for a square image of ``cfg.resolution``.

    ``(cx, cy)`` is measured from the top-left corner of the image, whose pixel ``(row i, column j)`` has its
    centre at ``(j + 0.5, i + 0.5)`` (nerfstudio's convention), so the optical axis passes through the corner
    shared by the four middle pixels.
    """
    f = cfg.resolution / 2 / math.tan(math.radians(cfg.fov_deg) / 2)
    return f, f, cfg.resolution / 2, cfg.resolution / 2


def camera_poses(radius: float, cfg: CaptureConfig, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Training and test camera-to-world poses ``([N, 4, 4], [M, 4, 4])`` looking at the origin.

    Test views are a second, independently rotated (``sphere``) or sampled (``hemisphere``) set, so they
    are held out from training.
    """
    rng = np.random.default_rng(seed)
    d = camera_distance(radius, cfg)
    if cfg.views == "sphere":
        train = fibonacci_directions(cfg.num_views)
        test = fibonacci_directions(cfg.num_test_views, _random_rotation(rng))
    else:
        train = hemisphere_directions(cfg.num_views, cfg, rng)
        test = hemisphere_directions(cfg.num_test_views, cfg, rng)
    return (
        np.stack([look_at(u * d) for u in train]) if len(train) else np.zeros((0, 4, 4)),
        np.stack([look_at(u * d) for u in test]) if len(test) else np.zeros((0, 4, 4)),
    )


# -- writing and reading ------------------------------------------------------------------------------------
def transforms_dict(c2w: np.ndarray, cfg: CaptureConfig, split: str) -> dict[str, Any]:
    """The ``transforms.json`` content for poses ``c2w`` [N, 4, 4] of one split (``train`` or ``test``)."""
    fx, fy, cx, cy = intrinsics(cfg)
    frames = [
        {
            "file_path": f"images/{split}_{i:03d}.png",
            "depth_file_path": f"depth/{split}_{i:03d}.npy",
            "transform_matrix": m.tolist(),
        }
        for i, m in enumerate(c2w)
    ]
    return {
        "camera_model": "OPENCV",  # pinhole without distortion; matrices use nerfstudio's OpenGL convention
        "fl_x": fx,
        "fl_y": fy,
        "cx": cx,
        "cy": cy,
        "w": cfg.resolution,
        "h": cfg.resolution,
        "camera_angle_x": math.radians(cfg.fov_deg),
        "camera_angle_y": math.radians(cfg.fov_deg),
        "depth_unit_scale_factor": 1.0,  # depth files are in metres
        "frames": frames,
    }


def write_transforms(folder: Path, split: str, c2w: np.ndarray, cfg: CaptureConfig) -> dict[str, Any]:
    """Write ``transforms.json`` (``split`` train) or ``transforms_<split>.json``; returns its content."""
    meta = transforms_dict(c2w, cfg, split)
    name = "transforms.json" if split == "train" else f"transforms_{split}.json"
    (folder / name).write_text(json.dumps(meta, indent=2) + "\n")
    return meta


def write_frame(folder: Path, frame: dict[str, Any], rgb: np.ndarray, depth: np.ndarray) -> None:
    """Write one view: the RGBA PNG (alpha 255 where ``depth`` > 0) and the float32 depth ``.npy``.

    Args:
        frame: a frame of :func:`transforms_dict` (its ``file_path`` and ``depth_file_path``).
        rgb: [H, W, 3] uint8. depth: [H, W] z-depth in metres, 0 where empty.
    """
    from PIL import Image

    alpha = np.where(depth > 0, 255, 0).astype(np.uint8)[..., None]
    # zlib level 1: ~2.5x faster than PIL's default 6 for ~15 % larger files (a few KB at 128 px).
    Image.fromarray(np.concatenate([rgb, alpha], -1), "RGBA").save(folder / frame["file_path"], compress_level=1)
    np.save(folder / frame["depth_file_path"], depth.astype(np.float32, copy=False))


def write_views(
    folder: Path,
    split: str,
    c2w: np.ndarray,
    rgb: np.ndarray,
    depth: np.ndarray,
    cfg: CaptureConfig,
    pool: Executor | None = None,
) -> list[Future[None]]:
    """Write RGBA PNGs (alpha from the depth mask), depth .npy files and ``transforms[_test].json``.

    Args:
        c2w: [N, 4, 4] camera-to-world poses; rgb: [N, H, W, 3] uint8; depth: [N, H, W] metres.
        pool: when given, the image files are written by its threads (PNG encoding releases the GIL); wait
            for the returned futures before using the folder. Without it, everything is written on return.
    """
    (folder / "images").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(parents=True, exist_ok=True)
    meta = write_transforms(folder, split, c2w, cfg)
    if pool is None:
        for frame, colour, z in zip(meta["frames"], rgb, depth):
            write_frame(folder, frame, colour, z)
        return []
    return [pool.submit(write_frame, folder, frame, colour, z) for frame, colour, z in zip(meta["frames"], rgb, depth)]
