"""A sensor's optical calibration: what ``tnf calibrate`` fits to real indenter presses and the simulator uses.

A calibration replaces the sensor's hand-set optics with measured ones:

* ``table``: the colour change ``[N, N, 3]`` (8-bit units) of a gel pixel as a function of the deformed surface's
  slope ``(sx, sy) = (dh/dx, dh/dy)`` (``h`` the outward height, ``x`` right, ``y`` up, dimensionless), sampled
  on a grid over ``[-max_slope, max_slope]^2`` and read bilinearly (slopes beyond the grid are clamped). The grid
  is regular in ``sign(s) |s / max_slope|^slope_power`` per axis: a power below 1 puts more nodes at small
  slopes, where a real gel's colour changes fastest.
  The image change of a pixel is ``table(slope) - table(undeformed slope)``: the role of the lights, ``contrast``
  and the Phong model. It is the data-driven shading of Taxim's polynomial table, indexed by slope instead of by
  gradient magnitude and direction.
* ``blur_sigma`` and ``noise_std``: the image blur (pixels) and pixel noise (8-bit units) measured on the frames.
* ``falloff``: the gel's decay length around a contact, as a multiple of its thickness (the simulator's fall-off).
* ``background``: the real no-contact frame ``[H, W, 3]`` uint8 at the sensor's size.

Stored as a folder: ``calibration.npz`` (the arrays and numbers), ``background.png`` and the artifact store's
``manifest.json``. A sensor built with ``calibration: PATH`` loads it (:func:`load_calibration`).
"""

from __future__ import annotations

import hashlib
import json
import pickle
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tnf.errors import TnfError

FILE = "calibration.npz"
UNREADABLE = (
    OSError,
    EOFError,
    KeyError,
    TypeError,
    ValueError,
    zipfile.BadZipFile,
    pickle.UnpicklingError,
    zlib.error,
)
"""What reading a truncated, corrupt or foreign ``calibration.npz`` raises."""


@dataclass
class Calibration:
    """Measured optics of one sensor at one image size (see the module docstring for each field)."""

    table: np.ndarray
    """``[N, N, 3]`` float32 colour change, 8-bit units, indexed ``[i(sy), j(sx)]``."""
    max_slope: float
    """Half-width of the slope grid (dimensionless)."""
    blur_sigma: float
    """Gaussian blur of the change image, pixels."""
    noise_std: float
    """Pixel noise, 8-bit units."""
    falloff: float
    """Gel fall-off length around a contact, multiples of the gel thickness."""
    background: np.ndarray
    """``[H, W, 3]`` uint8 no-contact frame."""
    slope_power: float = 1.0
    """Spacing of the table's nodes along each slope axis: regular in ``sign(s) |s / max_slope|^slope_power``."""

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels of the images this calibration describes."""
        return self.background.shape[1], self.background.shape[0]

    def resized(self, background: np.ndarray) -> Calibration:
        """The same optics for images of ``background``'s size ``[H, W, 3]`` uint8 (the same aspect ratio): the
        table and fall-off are independent of the image size; the blur is rescaled to the new pixels."""
        import dataclasses

        k = background.shape[1] / self.background.shape[1]
        if abs(background.shape[0] / self.background.shape[0] / k - 1) > 0.01:
            raise TnfError(
                f"calibration for {self.size[0]}x{self.size[1]} images cannot be resized to "
                f"{background.shape[1]}x{background.shape[0]}: the aspect ratios differ"
            )
        return dataclasses.replace(self, blur_sigma=self.blur_sigma * k, background=background.astype(np.uint8))

    def digest(self) -> str:
        """A short hash of the calibration's content (what decides whether touches made with it are stale)."""
        h = hashlib.sha256()
        for a in (self.table.astype(np.float32), self.background.astype(np.uint8)):
            h.update(np.ascontiguousarray(a).tobytes())
        numbers = [self.max_slope, self.blur_sigma, self.noise_std, self.falloff]
        if self.slope_power != 1.0:
            numbers.append(self.slope_power)
        h.update(json.dumps(numbers).encode())
        return h.hexdigest()[:16]

    def shade(self, slopes: np.ndarray) -> np.ndarray:
        """Table value at ``slopes [..., 2]`` = ``(sx, sy)``, bilinear and clamped -> ``[..., 3]`` float32.

        The simulator's kernel (``warp_gel``) reads the table the same way on the device.
        """
        n = self.table.shape[0]
        i0, j0, fy, fx = table_cells(slopes, n, self.max_slope, self.slope_power)
        fx, fy = fx[..., None], fy[..., None]
        t = self.table
        out = (
            t[i0, j0] * (1 - fx) * (1 - fy)
            + t[i0, j0 + 1] * fx * (1 - fy)
            + t[i0 + 1, j0] * (1 - fx) * fy
            + t[i0 + 1, j0 + 1] * fx * fy
        )
        return out.astype(np.float32)

    def save(self, folder: str | Path) -> None:
        """Write ``calibration.npz`` and ``background.png`` into ``folder``."""
        from PIL import Image

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        np.savez(
            folder / FILE,
            table=self.table.astype(np.float32),
            max_slope=self.max_slope,
            blur_sigma=self.blur_sigma,
            noise_std=self.noise_std,
            falloff=self.falloff,
            background=self.background.astype(np.uint8),
            slope_power=self.slope_power,
        )
        Image.fromarray(self.background.astype(np.uint8)).save(folder / "background.png")


def table_cells(
    slopes: np.ndarray, n: int, max_slope: float, power: float = 1.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where slopes ``[..., 2]`` ``(sx, sy)`` fall in an ``n x n`` table: the cell's first row and column
    ``[...]`` int and the fractions ``[...]`` along rows (sy) and columns (sx), clamped to the grid."""
    s = np.clip(slopes, -max_slope, max_slope) / max_slope
    if power != 1.0:
        s = np.sign(s) * np.abs(s) ** power
    f = (s + 1.0) / 2.0 * (n - 1)
    j0 = np.clip(np.floor(f[..., 0]).astype(int), 0, n - 2)
    i0 = np.clip(np.floor(f[..., 1]).astype(int), 0, n - 2)
    return i0, j0, f[..., 1] - i0, f[..., 0] - j0


def load_calibration(path: str | Path) -> Calibration:
    """Read a calibration folder written by ``tnf calibrate`` (or its ``calibration.npz``). A missing, unreadable
    or inconsistent file is a one-line TnfError naming it."""
    p = Path(path).expanduser()
    f = p / FILE if p.is_dir() else p
    if not f.is_file():
        raise TnfError(f"sensor calibration not found: {p} (run `tnf calibrate` first, or set sensor.calibration)")
    try:
        d = np.load(f)
        if not isinstance(d, np.lib.npyio.NpzFile):
            raise ValueError("a single array, not an .npz archive")
        with d:
            cal = Calibration(
                table=d["table"].astype(np.float32),
                max_slope=float(d["max_slope"]),
                blur_sigma=float(d["blur_sigma"]),
                noise_std=float(d["noise_std"]),
                falloff=float(d["falloff"]),
                background=d["background"],
                slope_power=float(d["slope_power"]) if "slope_power" in d.files else 1.0,
            )
    except UNREADABLE as e:
        reason = (str(e).splitlines() or [""])[0] or type(e).__name__
        raise TnfError(
            f"sensor calibration {f} is not readable ({reason}); write it again with `tnf calibrate`"
        ) from None
    t = cal.table
    if t.ndim != 3 or t.shape[0] != t.shape[1] or t.shape[0] < 2 or t.shape[2] != 3 or not np.isfinite(t).all():
        raise TnfError(f"sensor calibration {f}: table must be a finite [N, N, 3] array, got {list(t.shape)}")
    bg = cal.background
    if bg.dtype != np.uint8 or bg.ndim != 3 or bg.shape[2] != 3:
        raise TnfError(
            f"sensor calibration {f}: background must be an [H, W, 3] uint8 image, got {list(bg.shape)} {bg.dtype}"
        )
    finite = np.isfinite([cal.max_slope, cal.blur_sigma, cal.noise_std, cal.falloff]).all()
    if not (finite and cal.max_slope > 0 and cal.blur_sigma >= 0 and cal.noise_std >= 0 and cal.falloff > 0):
        raise TnfError(
            f"sensor calibration {f}: max_slope and falloff must be > 0, blur_sigma and noise_std >= 0, all finite"
        )
    if not 0 < cal.slope_power <= 1:
        raise TnfError(f"sensor calibration {f}: slope_power must be in (0, 1], got {cal.slope_power}")
    return cal
