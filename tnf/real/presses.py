"""Indenter presses: real tactile frames of a known shape pressed into the gel, the data ``tnf calibrate`` fits.

A press folder, which any lab can record (docs/calibration.md gives the protocol)::

    <folder>/
        presses.json        what the frames show (below)
        background.png      the sensor's frame with nothing touching it
        frames/00000.png    one RGB frame per press, all of the background's size

``presses.json``::

    {
      "format": "tnf.presses/1",
      "mm_per_pixel": 0.0295,                           # gel size of one frame pixel, millimetres
      "indenter": {"shape": "sphere", "radius_mm": 2.0},
      "background": "background.png",
      "presses": [
        {"image": "frames/00000.png", "center_px": [340, 224], "contact_radius_px": 39},
        {"image": "frames/00001.png", "center_px": [320, 240], "depth_mm": 0.4},
        ...
      ]
    }

``center_px`` is the contact's centre as ``[column, row]`` pixels (row 0 at the top). Each press gives either the
radius of its contact circle in pixels, as annotated on the frame, or ``depth_mm``: how far the indenter moved
past first contact. The two are tied by geometry, as in Taxim: the circle is where the sphere (radius ``R``)
crosses the undeformed gel surface, ``a = sqrt(R^2 - (R - depth)^2)``; inside it tnf's simulated gel takes the
sphere's shape.

:func:`import_taxim` writes such a folder from the calibration recordings that the ``taxim`` package ships
(``taxim/calib/<sensor>/dataPack.npz``: frames in OpenCV's BGR order, a 4 mm ball). :func:`load_presses`
reads and checks one; every problem is one line naming the file and the press. :func:`check_depths` checks
depths against the indenter's radius wherever they are scaled.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tnf.artifacts import ArtifactStore
from tnf.errors import TnfError
from tnf.sensors.base import Sensor, load_background

FORMAT = "tnf.presses/1"
INDEX = "presses.json"
SHAPES = ("sphere",)
TAXIM_BALL_RADIUS_MM = 2.0
"""Radius of the ball Taxim's calibration recordings were pressed with (4 mm diameter)."""


@dataclass(frozen=True)
class Press:
    """One frame of the indenter pressed into the gel."""

    image: Path
    """The frame's file."""
    center: tuple[float, float]
    """Contact centre ``(column, row)``, pixels of the recorded frame."""
    contact_radius_mm: float
    """Radius of the contact circle on the gel, millimetres."""
    depth_mm: float
    """How far the indenter moved past first contact, millimetres (tnf's contact model ties it to the radius)."""


@dataclass(frozen=True)
class PressSet:
    """A checked press folder: frames, background and the indenter's geometry."""

    folder: Path
    mm_per_pixel: float
    """Gel size of one frame pixel, millimetres."""
    radius_mm: float
    """Radius of the spherical indenter, millimetres."""
    width: int
    """Frame width, pixels."""
    height: int
    """Frame height, pixels."""
    presses: tuple[Press, ...]
    background_path: Path

    def __len__(self) -> int:
        return len(self.presses)

    def background(self) -> np.ndarray:
        """``[height, width, 3]`` uint8 RGB no-contact frame."""
        return _read_rgb(self.background_path)

    def frame(self, i: int) -> np.ndarray:
        """``[height, width, 3]`` uint8 RGB frame of press ``i``."""
        return _read_rgb(self.presses[i].image)

    def contact_radius_px(self, i: int) -> float:
        """Contact radius of press ``i`` in frame pixels."""
        return self.presses[i].contact_radius_mm / self.mm_per_pixel


def depth_from_contact_radius(radius_mm: float, contact_mm: float) -> float:
    """Depth past first contact (mm) at which a sphere of ``radius_mm`` crosses the gel in a circle of
    ``contact_mm`` (0 to ``radius_mm``; a TnfError outside)."""
    if not 0 <= contact_mm <= radius_mm:
        raise TnfError(f"contact radius {contact_mm:g} mm is outside 0 to the indenter's radius {radius_mm:g} mm")
    return radius_mm - math.sqrt(radius_mm**2 - contact_mm**2)


def contact_radius_from_depth(radius_mm: float, depth_mm: float) -> float:
    """Contact radius (mm) of a sphere of ``radius_mm`` pressed ``depth_mm`` past first contact (0 to
    ``radius_mm``; a TnfError outside)."""
    if not 0 <= depth_mm <= radius_mm:
        raise TnfError(f"depth {depth_mm:g} mm is outside 0 to the indenter's radius {radius_mm:g} mm")
    return math.sqrt(radius_mm**2 - (radius_mm - depth_mm) ** 2)


def check_depths(
    depths_mm: Sequence[float] | np.ndarray, radius_mm: float, where: str, presses: Sequence[int] | None = None
) -> np.ndarray:
    """``depths_mm`` ``[N]`` (millimetres past first contact) as a float64 array, after checking that each is
    finite, > 0 and smaller than the spherical indenter's ``radius_mm``.

    Raises a one-line TnfError ``"<where>: press <k>: ..."``: ``where`` names the file (and any factor applied
    to the depths), ``presses`` numbers the presses as in their folder (default ``0 .. N-1``).
    """
    d = np.asarray(depths_mm, dtype=np.float64).reshape(-1)
    numbers = list(range(len(d))) if presses is None else list(presses)
    if len(numbers) != len(d):
        raise ValueError(f"check_depths: {len(d)} depths, {len(numbers)} press numbers")
    for k, v in zip(numbers, d.tolist()):
        if not (math.isfinite(v) and v > 0):
            raise TnfError(f"{where}: press {k}: depth {v:g} mm must be a finite number > 0")
        if v >= radius_mm:
            raise TnfError(
                f"{where}: press {k}: depth {v:g} mm is not smaller than the indenter's radius {radius_mm:g} mm"
            )
    return d


def _read_rgb(path: Path) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise TnfError(f"press frame not found: {path}")
    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"), dtype=np.uint8).copy()
    except (UnidentifiedImageError, OSError) as e:
        raise TnfError(f"{path} is not a readable image: {e}") from None


def _image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of an 8-bit image file, after decoding all of it (a truncated file fails here)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            if im.mode.startswith(("I", "F")):  # PIL's 16- and 32-bit modes: converting to RGB clips them
                raise TnfError(f"{path} has {im.mode} pixels: press frames must be 8-bit RGB, saved 8 bits a channel")
            im.load()
            return im.size
    except (UnidentifiedImageError, OSError) as e:
        raise TnfError(f"{path} is not a readable image: {e}") from None


def _number(value: Any, where: str, positive: bool = True) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise TnfError(f"{where}: expected a finite number, got {value!r}")
    if positive and value <= 0:
        raise TnfError(f"{where}: must be > 0, got {value!r}")
    return float(value)


def load_presses(folder: str | Path) -> PressSet:
    """Read and check a press folder (see the module docstring). Raises a one-line TnfError on bad input."""
    folder = Path(folder).expanduser()
    index = folder / INDEX
    if not index.is_file():
        raise TnfError(f"no {INDEX} in {folder}: not a press folder (docs/calibration.md gives its layout)")
    try:
        meta = json.loads(index.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise TnfError(f"{index} is not valid JSON: {e}") from None
    if not isinstance(meta, dict):
        raise TnfError(f"{index}: expected a JSON object, got {type(meta).__name__}")
    if meta.get("format", FORMAT) != FORMAT:
        raise TnfError(f"{index}: format {meta['format']!r} is not {FORMAT!r}, the one tnf reads")
    for key in ("mm_per_pixel", "indenter", "presses"):
        if key not in meta:
            raise TnfError(f"{index}: missing key {key!r}")
    mmpp = _number(meta["mm_per_pixel"], f"{index}: mm_per_pixel")
    ind = meta["indenter"]
    if not isinstance(ind, dict) or ind.get("shape") not in SHAPES:
        shape = ind.get("shape") if isinstance(ind, dict) else ind
        raise TnfError(f"{index}: indenter.shape must be one of {', '.join(SHAPES)}, got {shape!r}")
    radius = _number(ind.get("radius_mm"), f"{index}: indenter.radius_mm")
    bg_path = folder / str(meta.get("background", "background.png"))
    if not bg_path.is_file():
        raise TnfError(f"{index}: background frame {bg_path.name} is missing (the sensor with nothing touching it)")
    width, height = _image_size(bg_path)
    entries = meta["presses"]
    if not isinstance(entries, list) or not entries:
        raise TnfError(f"{index}: presses must be a non-empty list")
    presses = []
    for i, entry in enumerate(entries):
        where = f"{index}: press {i}"
        if not isinstance(entry, dict) or "image" not in entry or "center_px" not in entry:
            raise TnfError(f"{where}: needs image and center_px")
        image = folder / str(entry["image"])
        if not image.is_file():
            raise TnfError(f"{where}: frame {entry['image']} not found")
        size = _image_size(image)
        if size != (width, height):
            raise TnfError(f"{where}: frame {entry['image']} is {size[0]}x{size[1]}, the background {width}x{height}")
        c = entry["center_px"]
        if not isinstance(c, (list, tuple)) or len(c) != 2:
            raise TnfError(f"{where}: center_px must be [column, row], got {c!r}")
        col, row = (_number(v, f"{where}: center_px", positive=False) for v in c)
        if not (0 <= col < width and 0 <= row < height):
            raise TnfError(f"{where}: center_px [{col:g}, {row:g}] is outside the {width}x{height} frame")
        has_r, has_d = "contact_radius_px" in entry, "depth_mm" in entry
        if has_r == has_d:
            raise TnfError(f"{where}: give exactly one of contact_radius_px and depth_mm")
        if has_r:
            contact = _number(entry["contact_radius_px"], f"{where}: contact_radius_px") * mmpp
            if contact >= radius:
                raise TnfError(
                    f"{where}: contact radius {contact:.3f} mm ({entry['contact_radius_px']} px) is not smaller "
                    f"than the indenter's radius {radius:g} mm (check mm_per_pixel and indenter.radius_mm)"
                )
            depth = depth_from_contact_radius(radius, contact)
        else:
            depth = _number(entry["depth_mm"], f"{where}: depth_mm")
            check_depths([depth], radius, str(index), presses=[i])
            contact = contact_radius_from_depth(radius, depth)
        presses.append(Press(image=image, center=(col, row), contact_radius_mm=contact, depth_mm=depth))
    return PressSet(
        folder=folder,
        mm_per_pixel=mmpp,
        radius_mm=radius,
        width=width,
        height=height,
        presses=tuple(presses),
        background_path=bg_path,
    )


def presses_digest(presses: PressSet) -> str:
    """A short hash of the press folder's content: its index, background and frames."""
    h = hashlib.sha256((presses.folder / INDEX).read_bytes())
    for path in (presses.background_path, *(p.image for p in presses.presses)):
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def taxim_recording(sensor: str) -> Path:
    """The folder of the ``taxim`` package's calibration recording of ``sensor`` (``gelsight_mini``, ``gelsight``)."""
    try:
        import taxim
    except ImportError:
        raise TnfError("the taxim package is not installed: pip install 'tnf[real]'") from None
    folder = Path(taxim.__file__).parent / "calib" / sensor
    if not (folder / "dataPack.npz").is_file():
        have = sorted(p.name for p in (Path(taxim.__file__).parent / "calib").iterdir() if p.is_dir())
        raise TnfError(f"taxim has no recording {sensor!r}; it has: {', '.join(have)}")
    return folder


def import_taxim(sensor: str, out: str | Path) -> PressSet:
    """Write the ``taxim`` package's recording of ``sensor`` as a press folder at ``out`` and return it checked.

    The frames are converted from OpenCV's BGR order to RGB; ``touch_center`` is ``(column, row)``.
    """
    from PIL import Image

    src = taxim_recording(sensor)
    params = json.loads((src / "params.json").read_text())
    with np.load(src / "dataPack.npz", allow_pickle=True) as d:
        f0, imgs = d["f0"], d["imgs"]
        centers, radii = d["touch_center"].astype(float), d["touch_radius"].astype(float)
    out = Path(out)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.ascontiguousarray(f0[..., ::-1])).save(out / "background.png")
    presses = []
    for i, img in enumerate(imgs):
        rel = f"frames/{i:05d}.png"
        Image.fromarray(np.ascontiguousarray(img[..., ::-1])).save(out / rel)
        presses.append({"image": rel, "center_px": centers[i].tolist(), "contact_radius_px": float(radii[i])})
    meta = {
        "format": FORMAT,
        "source": f"taxim package, calib/{sensor}/dataPack.npz",
        "mm_per_pixel": float(params["sensor"]["pixmm"]),
        "indenter": {"shape": "sphere", "radius_mm": TAXIM_BALL_RADIUS_MM},
        "background": "background.png",
        "presses": presses,
    }
    (out / INDEX).write_text(json.dumps(meta, indent=2) + "\n")
    return load_presses(out)


def resolve_presses(source: str, data_root: str | Path | None = None) -> PressSet:
    """A checked press folder from a setting: a folder path, or ``taxim:SENSOR`` for the recording the ``taxim``
    package ships, imported once into ``<data_root>/presses/taxim_SENSOR/``."""
    source = str(source)
    if source.startswith("taxim:"):
        recording = source.split(":", 1)[1]
        folder = ArtifactStore(data_root).path("presses", f"taxim_{recording}")
        return load_presses(folder) if (folder / INDEX).is_file() else import_taxim(recording, folder)
    return load_presses(Path(source))


@dataclass
class SensorPresses:
    """Presses at the sensor's image size."""

    background: np.ndarray
    """``[H, W, 3]`` uint8."""
    frames: np.ndarray
    """``[N, H, W, 3]`` uint8."""
    centers: np.ndarray
    """``[N, 2]`` float, contact centres ``(column, row)`` in sensor pixels (pixel centres at whole numbers)."""
    radii: np.ndarray
    """``[N]`` float, contact radii in sensor pixels."""
    depths: np.ndarray
    """``[N]`` float, metres past first contact."""
    indices: list[int]
    """Which presses of the folder these are."""


def check_indices(presses: PressSet, indices: Sequence[int], where: str = "") -> None:
    """A one-line TnfError ``"<where>: press <k> does not exist ..."`` unless every index names a press of the
    folder; ``where`` names the setting that holds them."""
    n = len(presses)
    bad = [i for i in indices if not 0 <= i < n]
    if bad:
        prefix = f"{where}: " if where else ""
        raise TnfError(f"{prefix}press {bad[0]} does not exist: {presses.folder} has presses 0-{n - 1}")


def at_sensor_size(presses: PressSet, sensor: Sensor, indices: Sequence[int]) -> SensorPresses:
    """The presses ``indices`` resized to ``sensor``'s image size, after checking that the geometry matches."""
    check_indices(presses, indices)
    given = [presses.presses[i].depth_mm for i in indices]
    depths_mm = check_depths(given, presses.radius_mm, str(presses.folder / INDEX), presses=indices)
    sx, sy = sensor.width / presses.width, sensor.height / presses.height
    if abs(sx / sy - 1) > 0.01:
        raise TnfError(
            f"sensor {sensor.name!r} images are {sensor.width}x{sensor.height}, the presses' {presses.width}x"
            f"{presses.height}: the aspect ratios differ; give the sensor that recorded them (sensor=gelsight_mini "
            f"for Taxim's GelSight Mini) a size of the presses' aspect ratio, e.g. sensor.width={sensor.width} "
            f"sensor.height={round(sensor.width * presses.height / presses.width)}"
        )
    want = presses.mm_per_pixel / sx  # mm per sensor pixel
    have = 1e3 * float(np.mean(sensor.pixel_size()))
    if abs(have / want - 1) > 0.02:
        markers = ""
        if sensor.decorates:  # a sensor that draws markers over its images
            setting = " (sensor.markers=false)" if hasattr(sensor.cfg, "markers") else ""
            markers = f"; it also draws markers onto its images, which a marker-free recording lacks{setting}"
        raise TnfError(
            f"sensor {sensor.name!r} sees {have:.4f} mm per pixel, the presses {want:.4f} mm at its size "
            f"({presses.mm_per_pixel} mm at {presses.width}x{presses.height}): set sensor.fov or "
            f"sensor.camera_distance to match{markers}"
        )
    bg = load_background(presses.background_path, sensor.width, sensor.height)
    frames = np.stack([load_background(presses.presses[i].image, sensor.width, sensor.height) for i in indices])
    centers = np.array([[(c + 0.5) * sx - 0.5 for c in presses.presses[i].center] for i in indices], dtype=float)
    radii = np.array([presses.contact_radius_px(i) * sx for i in indices], dtype=float)
    depths = depths_mm * 1e-3
    return SensorPresses(bg, frames, centers.reshape(-1, 2), radii, depths, list(indices))


def sphere_gaps(sensor: Sensor, centers: np.ndarray, radius_m: float) -> np.ndarray:
    """Gaps ``[N, H, W]`` float32 (metres, along the sensor's axis) from the undeformed gel to a sphere of
    ``radius_m`` whose lowest point faces each centre ``(column, row)`` in pixels; inf where it is not above."""
    fx, fy, cx, cy = sensor.intrinsics()
    d = sensor.cfg.camera_distance
    x, y = sensor.gel_grid()
    h0 = sensor.gel_surface()
    out = []
    for col, row in np.asarray(centers, dtype=float).reshape(-1, 2):
        x0 = (col + 0.5 - cx) / fx * d
        y0 = -(row + 0.5 - cy) / fy * d
        r2 = (x - x0) ** 2 + (y - y0) ** 2
        inside = r2 < radius_m**2
        under = np.sqrt(np.where(inside, radius_m**2 - r2, 0.0))
        out.append(np.where(inside, -under - h0, np.inf))  # only differences matter
    return np.stack(out).astype(np.float32)


def disk_masks(shape: tuple[int, int], centers: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """``[N, H, W]`` bool: pixels whose centre lies within ``radii`` pixels of ``centers`` ``(column, row)``."""
    rows, cols = np.mgrid[: shape[0], : shape[1]]
    c = np.asarray(centers, dtype=float).reshape(-1, 2)
    r = np.asarray(radii, dtype=float).reshape(-1)
    return (cols[None] - c[:, 0, None, None]) ** 2 + (rows[None] - c[:, 1, None, None]) ** 2 <= r[:, None, None] ** 2
