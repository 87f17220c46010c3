"""Rendering the RGB-D side of each pair: a camera at the touch's start pose, looking along the sensor's axis.

The paper's matching criterion: the camera has the sensor's orientation and the sensor sits on the camera's
centre ray. A touch's ``start_c2w`` is the sensor's pose before it advances (OpenGL convention: the sensor
looks along its -z axis), so it is used as the camera pose as it is.

The crop (``Framing``) shows the gel's footprint where the gel first meets the surface, so an RGB-D pixel
covers the same patch of gel in every pair, however far the start pose is from the object; depth is measured
from that first contact, which the generator then sees as 0.5. With ``crop_extent="sensor"`` the crop is the
patch the tactile image itself shows, so that the two images are pixel-aligned.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from tnf.artifacts import MANIFEST, read_json
from tnf.cameras import camera_rays
from tnf.data.preprocess import (
    SIZE,
    contact_depth,
    footprint_px,
    gel_size_m,
    preprocess_rgbd,
    resize,
    resize_uint8,
)
from tnf.data.settings import PairSettings
from tnf.errors import TnfError
from tnf.touches import TouchRecord, touch_records_of


@dataclass
class TouchItem:
    """One object's touches as ``tnf touch`` writes them (``<root>/touch/<sensor>/<source>/<object>/``)."""

    folder: Path
    manifest: dict[str, Any]
    touches: list[TouchRecord]  # the manifest's ``touches``, in order

    @classmethod
    def load(cls, folder: str | os.PathLike[str]) -> TouchItem:
        folder = Path(folder)
        manifest = read_json(folder / MANIFEST, "touch manifest")
        touches = touch_records_of(manifest, folder / MANIFEST)
        _check_images(folder, [folder / "background.png", *(folder / t.image for t in touches)])
        return cls(folder, manifest, touches)

    def start_poses(self) -> np.ndarray:
        """[N, 4, 4] float64 camera-to-world start poses of the sensor."""
        return np.asarray([t.start_c2w for t in self.touches], dtype=np.float64).reshape(-1, 4, 4)

    def contact_distances(self) -> np.ndarray:
        """[N] metres from the start pose to the contact point along the sensor's axis (-z); the contact pose's
        position stands in for a touch without a contact point; NaN for one without either."""
        poses = self.start_poses()
        pts = np.asarray([_contact_point(t) for t in self.touches], dtype=np.float64).reshape(-1, 3)
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
            return resize_uint8(_read_png(self.folder / self.touches[i].image), out)

        with ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1)) as pool:
            return np.stack(list(pool.map(load, rows)))


def _contact_point(t: TouchRecord) -> Sequence[float]:
    """A touch's contact point [3] (metres), its contact pose's position without one, else NaNs (unknown)."""
    if t.contact_point is not None:
        return t.contact_point
    return [math.nan] * 3 if t.contact_c2w is None else [r[3] for r in t.contact_c2w[:3]]


def _read_png(path: Path) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"))
    except FileNotFoundError:
        raise TnfError(f"image not found: {path}; rerun `tnf touch` for this object") from None
    except (UnidentifiedImageError, OSError, SyntaxError) as e:
        raise TnfError(f"{path} is not a readable image ({e}); {_REDO}") from None


_REDO = "remove the object's touches (`tnf clean touch SENSOR/SOURCE/OBJECT`) and rerun `tnf touch`"


def _check_images(folder: Path, paths: Sequence[Path]) -> None:
    """Every image of a touch item in ``folder`` exists and is whole (its chunks' checksums), before any rendering
    starts: a corrupt file is named here, not in a traceback after minutes of work."""
    from PIL import Image, UnidentifiedImageError

    for path in paths:
        if not path.is_file():
            raise TnfError(f"image not found: {path}; {_REDO}")
        try:
            with Image.open(path) as im:
                im.verify()
        except (UnidentifiedImageError, OSError, SyntaxError) as e:
            raise TnfError(f"{path} is not a readable image ({e}); {_REDO}") from None


CROP_DISTANCES = ("contact", "fixed")
"""How far away the gel footprint that sizes each RGB-D crop is measured (``pair.crop_distance``)."""
CROP_EXTENTS = ("footprint", "sensor")
"""What each per-view crop shows (``pair.crop_extent``; see ``Framing``)."""
DEPTH_NORMS = ("contact", "center", "minmax")
"""Depth normalisations (``pair.depth_norm``; see ``preprocess_rgbd``)."""
PROBE_PX = 64
"""Side of the low-resolution depth render that finds where the gel would first meet the surface (at most the
crop's own render size, so that a small ``render_px`` on a CPU also makes the probe cheaper)."""
PROBE_NEAR = 0.5
"""The probe sees the whole footprint of contacts down to this fraction of the reference distance."""


@dataclass(frozen=True)
class Framing:
    """How the RGB-D side of a pair is framed and normalised: the ``pair`` settings, stored in each dataset's
    manifest so that ``tnf generate`` frames novel poses exactly as the model's training data.

    ``crop_distance``:
      - ``contact``: each view's crop shows the gel footprint (times ``crop_margin``) at the depth where the
        gel first meets the surface, found from the scene's own depth: every image has the tactile image's
        physical scale, whatever the distance from the start pose to the object.
      - ``fixed``: one crop for every view, the footprint at ``footprint_distance`` (or ``crop_px`` pixels of
        the capture camera): the scale then varies with each touch's distance.

    ``crop_extent`` (per-view crops only):
      - ``footprint``: a square of ``crop_margin`` times the gel's larger side.
      - ``sensor``: exactly the gel patch the tactile image shows (``view_size``, from ``Sensor.view_size``),
        stretched to the square output like the tactile image: RGB-D pixel ``(i, j)`` and tactile pixel
        ``(i, j)`` then see the same point of the surface, which suits generators built on skip connections.
    """

    crop_distance: str = "contact"
    footprint_distance: float = 0.1
    """Reference distance in metres: the fixed crop's, and the contact crop's when no surface is in the
    footprint (the pair stage uses the touches' median; 0.1 m only when a fixed ``crop_px`` is set and no
    touch records its contact)."""
    crop_margin: float = 1.5
    crop_px: int | None = None
    """A fixed crop side in capture-camera pixels (overrides ``crop_distance``)."""
    depth_norm: str = "contact"
    depth_window: float = 0.04
    render_px: int | None = None
    crop_extent: str = "footprint"
    view_size: tuple[float, float] | None = None
    """The tactile image's gel patch ``(width, height)`` in metres, for ``crop_extent="sensor"`` (``with_sensor``
    fills it in; a dataset manifest stores it, so generation frames novel poses as the training data)."""

    def __post_init__(self) -> None:
        if self.crop_distance not in CROP_DISTANCES:
            raise TnfError(f"crop_distance must be one of {', '.join(CROP_DISTANCES)}, got {self.crop_distance!r}")
        if not (self.footprint_distance > 0 and math.isfinite(self.footprint_distance)):
            raise TnfError(f"footprint distance must be > 0 metres, got {self.footprint_distance}")
        if self.crop_margin <= 0:
            raise TnfError(f"crop_margin must be > 0, got {self.crop_margin}")
        if self.depth_norm not in DEPTH_NORMS:
            raise TnfError(f"depth_norm must be one of {', '.join(DEPTH_NORMS)}, got {self.depth_norm!r}")
        if self.depth_window <= 0:
            raise TnfError(f"depth_window must be > 0 metres, got {self.depth_window}")
        for name in ("crop_px", "render_px"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise TnfError(f"{name} must be at least 1 pixel or null, got {value}")
        if self.crop_extent not in CROP_EXTENTS:
            raise TnfError(f"crop_extent must be one of {', '.join(CROP_EXTENTS)}, got {self.crop_extent!r}")
        if self.crop_extent == "sensor" and not self.per_view:
            raise TnfError(
                "crop_extent=sensor frames each view at its contact: it needs crop_distance=contact and no crop_px"
            )
        if self.view_size is not None and not (len(self.view_size) == 2 and min(self.view_size) > 0):
            raise TnfError(f"view_size must be (width, height) > 0 metres, got {self.view_size}")

    @classmethod
    def from_settings(cls, settings: Mapping[str, Any] | PairSettings, **override: Any) -> Framing:
        """From the ``pair`` section (``PairSettings`` or a config node) or a dataset manifest's ``preprocess``."""
        if isinstance(settings, PairSettings):
            settings = dataclasses.asdict(settings)
        keys = {f: settings[f] for f in cls.__dataclass_fields__ if settings.get(f) is not None}
        keys.update({k: v for k, v in override.items() if v is not None})
        for k in ("footprint_distance", "crop_margin", "depth_window"):
            if k in keys:
                keys[k] = float(keys[k])
        for k in ("crop_px", "render_px"):
            if keys.get(k) is not None:
                keys[k] = int(keys[k])
        if keys.get("view_size") is not None:
            keys["view_size"] = tuple(float(v) for v in keys["view_size"])
        return cls(**keys)

    def with_sensor(self, sensor: Any) -> Framing:
        """This framing with ``view_size`` from ``sensor`` where ``crop_extent="sensor"`` needs it and lacks it."""
        if self.crop_extent != "sensor" or self.view_size is not None:
            return self
        w, h = sensor.view_size()
        return replace(self, view_size=(float(w), float(h)))

    @property
    def per_view(self) -> bool:
        """True when every view gets its own crop (``contact`` without a fixed ``crop_px``)."""
        return self.crop_distance == "contact" and self.crop_px is None

    def fixed_crop(self, focal: tuple[float, float], gel_size: tuple[float, float]) -> int:
        """The one crop side in capture-camera pixels when not ``per_view``."""
        if self.crop_px is not None:
            return int(self.crop_px)
        return max(1, int(math.ceil(footprint_px(focal, gel_size, self.footprint_distance, self.crop_margin))))


def render_intrinsics(
    fx: float, fy: float, crop_px: float, out: int = SIZE, render_px: int | None = None
) -> tuple[int, tuple[float, float, float, float]]:
    """Render size and intrinsics that show exactly the ``crop_px`` centre crop of a camera with focal
    lengths ``fx, fy`` (pixels), rendered directly at ``render_px`` pixels (default ``max(out, crop_px)``).
    A smaller ``render_px`` trades sharpness for speed (preprocessing resizes to ``out``), for CPU runs.

    Rendering only the crop (rather than the full image, then cropping) costs ``crop^2`` rays instead of
    ``W * H``; rendering a small crop at the output size keeps it sharp instead of upsampling it.
    """
    size = int(render_px) if render_px else max(out, int(math.ceil(crop_px)))
    s = size / crop_px
    return size, (fx * s, fy * s, size / 2, size / 2)


class Crops(NamedTuple):
    """What ``render_rgbd_crops`` returns (see there)."""

    rgb: np.ndarray
    depth: np.ndarray
    contact: np.ndarray
    points: np.ndarray | None = None


def render_rgbd_crops(
    scene: Any,
    c2w: torch.Tensor,
    focal: tuple[float, float],
    gel_size: tuple[float, float],
    framing: Framing,
    chunk: int | None = None,
    measure_contact: bool = False,
    with_points: bool = False,
) -> Crops:
    """Render and preprocess the RGB-D crops of B sensor poses, framed by ``framing``.

    Args:
        scene: a ``tnf.scenes.Scene`` of the object.
        c2w: [B, 4, 4] sensor (= camera) poses on the scene's device, looking along -z.
        focal: ``(fx, fy)`` of the capture camera, in pixels: crops are measured in its pixels.
        gel_size: the sensor's gel (width, height) in metres.
        framing: the crop and depth settings.
        chunk: rays per chunk inside the scene renderer.
        measure_contact: find the first-contact depth even when the framing does not need it.
        with_points: also return each crop pixel's surface point (``crop_points``).

    Returns:
        ``Crops``: ``rgb`` uint8 [B, 128, 128, 3], ``depth`` float16 [B, 128, 128] in [0, 1], ``contact``
        float64 [B], the depth in metres at which the gel first meets the surface (NaN where no surface lies in
        the footprint; all NaN unless the crop, the depth normalisation or ``measure_contact`` needs it), and
        with ``with_points`` ``points`` float32 [B, 128, 128, 3].
    """
    b, dev = len(c2w), c2w.device
    fx, fy = focal
    contact = torch.full((b,), math.nan, device=dev)
    if framing.per_view or framing.depth_norm == "contact" or measure_contact:
        # Where the gel would first meet the surface: the nearest hit inside the footprint, on a coarse render
        # wide enough for contacts down to PROBE_NEAR of the reference distance.
        n = min(PROBE_PX, int(framing.render_px or PROBE_PX))
        side = footprint_px(focal, gel_size, PROBE_NEAR * framing.footprint_distance)
        k = torch.tensor([fx * n / side, fy * n / side, n / 2, n / 2], device=dev)
        probe = scene.render_rgbd(c2w, k.expand(b, 4), n, n, chunk=chunk)
        depth = probe["depth"]
        if probe.get("opacity") is not None:
            depth = torch.where(probe["opacity"] >= 0.5, depth, torch.zeros_like(depth))
        contact = contact_depth(depth, k, gel_size)
    ref = torch.where(torch.isfinite(contact), contact, torch.full_like(contact, framing.footprint_distance))
    if framing.per_view:
        size = int(framing.render_px or SIZE)
        centre = torch.full_like(ref, size / 2)
        if framing.crop_extent == "sensor":
            if framing.view_size is None:
                raise TnfError("crop_extent=sensor needs the sensor's view_size (Framing.with_sensor)")
            # The view_size patch at the contact depth spans the render: x = +-w/2 at u = 0 and u = size.
            w, h = framing.view_size
            intr = torch.stack([size * ref / w, size * ref / h, centre, centre], 1)
        else:
            s = size / (footprint_px(focal, gel_size, 1.0, framing.crop_margin) / ref)  # crop in capture pixels
            intr = torch.stack([fx * s, fy * s, centre, centre], 1)
    else:
        size, k4 = render_intrinsics(fx, fy, framing.fixed_crop(focal, gel_size), render_px=framing.render_px)
        intr = torch.tensor(k4, dtype=torch.float32, device=dev).expand(b, 4)
    r = scene.render_rgbd(c2w, intr.float(), size, size, chunk=chunk)
    rgb8, depth01 = preprocess_rgbd(
        r["rgb"], r["depth"], r.get("opacity"), crop_px=size,
        depth_norm=framing.depth_norm, depth_window=framing.depth_window, contact=ref,  # type: ignore[arg-type]
    )  # fmt: skip
    points = crop_points(r["depth"], r.get("opacity"), c2w, intr.float()) if with_points else None
    return Crops(rgb8, depth01, contact.double().cpu().numpy(), points)


def crop_points(
    depth: torch.Tensor, opacity: torch.Tensor | None, c2w: torch.Tensor, intrinsics: torch.Tensor, out: int = SIZE
) -> np.ndarray:
    """The surface point that each pixel of rendered crops sees, in the object's (the scene's) frame.

    Args:
        depth: [B, S, S] z-depth in metres, 0 where no surface was hit.
        opacity: [B, S, S] accumulated opacity (pixels under 0.5 count as empty), or None.
        c2w: [B, 4, 4] the cameras that rendered them (OpenGL: looking along -z).
        intrinsics: [B, 4] their ``(fx, fy, cx, cy)`` in pixels.
        out: output side in pixels (bilinear, as the crops' depth).

    Returns:
        float32 [B, out, out, 3] in metres; NaN where no surface was hit (or a resized pixel mixes in one).
        Unlike the normalised depth, they say where on the object the crop lies, the same for every view.
    """
    b, h, w = depth.shape
    origins, dirs, z_scale = camera_rays(c2w, intrinsics, w, h)
    hit = depth > 0
    if opacity is not None:
        hit &= opacity >= 0.5
    p = origins + dirs * (depth / z_scale)[..., None]
    p = torch.where(hit[..., None], p, torch.full_like(p, math.nan))
    if (h, w) != (out, out):  # NaN spreads to every output pixel that mixes an empty one in
        p = resize(p.permute(0, 3, 1, 2), out).permute(0, 2, 3, 1)
    return p.float().cpu().numpy()


def render_pairs_for_touches(
    scene: Any,
    touch_item: TouchItem | str | os.PathLike[str],
    sensor: Any,
    framing: Framing,
    *,
    focal: tuple[float, float],
    rows: Sequence[int] | None = None,
    device: str = "cpu",
    render_batch: int = 64,
    render_chunk: int | None = None,
    on_batch: Callable[[int], None] | None = None,
    with_points: bool = False,
) -> dict[str, np.ndarray]:
    """Render and preprocess the RGB-D image of each touch of one object, and load its tactile images.

    Args:
        scene: a ``tnf.scenes.Scene`` of the object (fitted, or the ground-truth mesh).
        touch_item: the object's touch folder or a loaded ``TouchItem``.
        sensor: the sensor (its gel size frames the crops).
        framing: crop and depth settings (see ``Framing``).
        focal: ``(fx, fy)`` in pixels of the camera the crop is measured in (the capture camera).
        rows: which touches (positions in the manifest's list); default all.
        device: torch device to render on.
        render_batch: touches rendered per batch (bounds renderer memory).
        render_chunk: rays per chunk inside the scene renderer.
        on_batch: called with the number of touches after each rendered batch (progress).
        with_points: also return ``points`` float32 [N, 128, 128, 3], each pixel's surface point
            (``crop_points``).

    Returns:
        ``rgb`` uint8 [N, 128, 128, 3], ``depth`` float16 [N, 128, 128] in [0, 1], ``tactile`` uint8
        [N, 128, 128, 3], ``background`` uint8 [128, 128, 3], ``touch_index`` int32 [N].
    """
    item = touch_item if isinstance(touch_item, TouchItem) else TouchItem.load(touch_item)
    rows = list(range(len(item.touches))) if rows is None else list(rows)
    gel = gel_size_m(sensor)
    poses = item.start_poses()
    rgb_out = np.empty((len(rows), SIZE, SIZE, 3), np.uint8)
    depth_out = np.empty((len(rows), SIZE, SIZE), np.float16)
    points_out = np.empty((len(rows), SIZE, SIZE, 3), np.float32) if with_points else None
    for s in range(0, len(rows), render_batch):
        sel = rows[s : s + render_batch]
        c2w = torch.as_tensor(poses[sel], dtype=torch.float32, device=device)
        with torch.no_grad():
            crops = render_rgbd_crops(scene, c2w, focal, gel, framing, chunk=render_chunk, with_points=with_points)
        rgb_out[s : s + len(sel)], depth_out[s : s + len(sel)] = crops.rgb, crops.depth
        if points_out is not None:
            points_out[s : s + len(sel)] = crops.points
        if on_batch is not None:
            on_batch(len(sel))
    return {
        **({"points": points_out} if points_out is not None else {}),
        "rgb": rgb_out,
        "depth": depth_out,
        "tactile": item.tactile(rows) if rows else np.empty((0, SIZE, SIZE, 3), np.uint8),
        "background": item.background(),
        "touch_index": np.asarray([item.touches[i].index for i in rows], dtype=np.int32),
    }
