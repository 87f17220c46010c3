"""Rendering the RGB-D side of each pair: a camera at the touch's start pose, looking along the sensor's axis.

The paper's matching criterion: the camera has the sensor's orientation and the sensor sits on the camera's
centre ray. A touch's ``start_c2w`` is the sensor's pose before it advances (OpenGL convention: the sensor
looks along its -z axis), so it is used as the camera pose as it is.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from tnf.artifacts import MANIFEST, read_json
from tnf.data.preprocess import SIZE, crop_for_sensor, preprocess_rgbd, resize_uint8
from tnf.errors import TnfError


@dataclass
class TouchItem:
    """One object's touches as ``tnf touch`` writes them (``<root>/touch/<sensor>/<source>/<object>/``)."""

    folder: Path
    manifest: dict[str, Any]

    @classmethod
    def load(cls, folder: str | os.PathLike[str]) -> TouchItem:
        folder = Path(folder)
        manifest = read_json(folder / MANIFEST, "touch manifest")
        touches = manifest.get("touches") if isinstance(manifest, dict) else None
        if not isinstance(touches, list):
            raise TnfError(f"touch manifest {folder / MANIFEST} has no 'touches' list; rerun `tnf touch`")
        where = folder / MANIFEST
        for i, t in enumerate(touches):
            if not isinstance(t, dict):
                raise TnfError(f"touch manifest {where}: touch {i} is not an object; rerun `tnf touch`")
            for key in ("index", "split", "image", "start_c2w"):
                if key not in t:
                    raise TnfError(f"touch manifest {where}: a touch lacks {key!r}; rerun `tnf touch`")
            if not isinstance(t["image"], str) or not isinstance(t["split"], str):
                raise TnfError(f"touch manifest {where}: touch {i} 'image' and 'split' must be strings")
            try:
                pose = np.asarray(t["start_c2w"], dtype=np.float64)
            except (ValueError, TypeError):
                pose = np.zeros(0)
            if pose.shape != (4, 4) or not np.isfinite(pose).all():
                raise TnfError(f"touch manifest {where}: touch {i} start_c2w must be a finite 4x4 matrix")
            if t.get("contact_point") is not None:
                try:
                    point = np.asarray(t["contact_point"], dtype=np.float64)
                except (ValueError, TypeError):
                    point = np.zeros(0)
                if point.shape != (3,):
                    raise TnfError(f"touch manifest {where}: touch {i} contact_point must be 3 numbers (metres)")
        return cls(folder, manifest)

    @property
    def touches(self) -> list[dict[str, Any]]:
        return self.manifest["touches"]

    def start_poses(self) -> np.ndarray:
        """[N, 4, 4] float64 camera-to-world start poses of the sensor."""
        return np.asarray([t["start_c2w"] for t in self.touches], dtype=np.float64).reshape(-1, 4, 4)

    def contact_distances(self) -> np.ndarray:
        """[N] metres from the start pose to the contact point along the sensor's axis (-z)."""
        poses = self.start_poses()
        pts = np.asarray([t.get("contact_point", t.get("contact_c2w", np.eye(4))) for t in self.touches], float)
        if pts.ndim == 3:  # only contact poses known: use their positions
            pts = pts[:, :3, 3]
        axis = -poses[:, :3, 2]
        return np.einsum("nk,nk->n", pts - poses[:, :3, 3], axis)

    def background(self, out: int = SIZE) -> np.ndarray:
        """The sensor's background image, uint8 [out, out, 3]."""
        return resize_uint8(_read_png(self.folder / "background.png"), out)

    def tactile(self, rows: Sequence[int], out: int = SIZE) -> np.ndarray:
        """Tactile images of touches ``rows`` (positions in ``touches``), uint8 [len(rows), out, out, 3].

        Decoded and resized by a few threads (PIL releases the GIL there): hundreds of PNGs per object.
        """
        from concurrent.futures import ThreadPoolExecutor

        def load(i: int) -> np.ndarray:
            return resize_uint8(_read_png(self.folder / self.touches[i]["image"]), out)

        with ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1)) as pool:
            return np.stack(list(pool.map(load, rows)))


def _read_png(path: Path) -> np.ndarray:
    from PIL import Image

    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"))
    except FileNotFoundError:
        raise TnfError(f"image not found: {path}; rerun `tnf touch` for this object") from None


def render_intrinsics(
    fx: float, fy: float, crop_px: int, out: int = SIZE, render_px: int | None = None
) -> tuple[int, tuple[float, float, float, float]]:
    """Render size and intrinsics that show exactly the ``crop_px`` centre crop of a camera with focal
    lengths ``fx, fy`` (pixels), rendered directly at ``render_px`` pixels (default ``max(out, crop_px)``).
    A smaller ``render_px`` trades sharpness for speed (preprocessing resizes to ``out``), for CPU runs.

    Rendering only the crop (rather than the full image, then cropping) costs ``crop^2`` rays instead of
    ``W * H``; rendering a small crop at the output size keeps it sharp instead of upsampling it.
    """
    size = int(render_px) if render_px else max(out, crop_px)
    s = size / crop_px
    return size, (fx * s, fy * s, size / 2, size / 2)


def render_pairs_for_touches(
    scene: Any,
    touch_item: TouchItem | str | os.PathLike[str],
    sensor: Any,
    cfg: Mapping[str, Any],
    *,
    focal: tuple[float, float],
    crop_px: int | None = None,
    rows: Sequence[int] | None = None,
    device: str = "cpu",
    on_batch: Callable[[int], None] | None = None,
) -> dict[str, np.ndarray]:
    """Render and preprocess the RGB-D image of each touch of one object, and load its tactile images.

    Args:
        scene: a ``tnf.scenes.Scene`` of the object (fitted, or the ground-truth mesh).
        touch_item: the object's touch folder or a loaded ``TouchItem``.
        sensor: the sensor (sizes the crop when ``crop_px`` and ``cfg["crop_px"]`` are None).
        cfg: the pair settings: ``depth_norm``, ``depth_window`` (m), ``render_batch``, ``render_chunk``,
            ``crop_px``, ``crop_margin``.
        focal: ``(fx, fy)`` in pixels of the camera the crop is measured in (the capture camera).
        crop_px: crop side in that camera's pixels; default ``cfg["crop_px"]``, else the sensor's gel
            footprint at the median start-to-contact distance of these touches.
        rows: which touches (positions in the manifest's list); default all.
        device: torch device to render on.
        on_batch: called with the number of touches after each rendered batch (progress).

    Returns:
        ``rgb`` uint8 [N, 128, 128, 3], ``depth`` float16 [N, 128, 128] in [0, 1], ``tactile`` uint8
        [N, 128, 128, 3], ``background`` uint8 [128, 128, 3], ``touch_index`` int32 [N], ``crop_px`` int.
    """
    item = touch_item if isinstance(touch_item, TouchItem) else TouchItem.load(touch_item)
    rows = list(range(len(item.touches))) if rows is None else list(rows)
    if crop_px is None:
        crop_px = cfg.get("crop_px")
    if crop_px is None:
        dist = float(np.median(item.contact_distances()[rows])) if rows else 0.05
        crop_px = crop_for_sensor(sensor, (*focal, 0, 0), distance=dist, margin=float(cfg.get("crop_margin", 1.0)))
    size, intr = render_intrinsics(focal[0], focal[1], int(crop_px), render_px=cfg.get("render_px"))
    poses = item.start_poses()
    batch = int(cfg.get("render_batch", 64))
    rgb_out = np.empty((len(rows), SIZE, SIZE, 3), np.uint8)
    depth_out = np.empty((len(rows), SIZE, SIZE), np.float16)
    intr_t = torch.tensor(intr, dtype=torch.float32, device=device)
    for s in range(0, len(rows), batch):
        sel = rows[s : s + batch]
        c2w = torch.as_tensor(poses[sel], dtype=torch.float32, device=device)
        with torch.no_grad():
            r = scene.render_rgbd(c2w, intr_t.expand(len(sel), 4), size, size, chunk=cfg.get("render_chunk"))
        rgb_out[s : s + len(sel)], depth_out[s : s + len(sel)] = preprocess_rgbd(
            r["rgb"],
            r["depth"],
            r.get("opacity"),
            crop_px=size,
            depth_norm=cfg.get("depth_norm", "center"),
            depth_window=float(cfg.get("depth_window", 0.04)),
        )
        if on_batch is not None:
            on_batch(len(sel))
    return {
        "rgb": rgb_out,
        "depth": depth_out,
        "tactile": item.tactile(rows) if rows else np.empty((0, SIZE, SIZE, 3), np.uint8),
        "background": item.background(),
        "touch_index": np.asarray([item.touches[i]["index"] for i in rows], dtype=np.int32),
        "crop_px": np.int64(crop_px),
    }
