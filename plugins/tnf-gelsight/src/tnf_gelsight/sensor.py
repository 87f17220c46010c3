"""GelSight Mini-like sensor: a flat 18.6 x 14.3 mm gel lit from its four edges, with a printed marker grid.

The image is landscape, 320x240 (W x H): the gel is wider (x) than tall (y), so its long side runs along the
image rows, as in the GelSight Mini's own video. Frames and units follow ``tnf.sensors.base``: sensor frame =
camera frame (OpenGL: looking along -z, +x right, +y up), metres; images ``[H, W, 3]`` uint8.

Markers: black dots printed on the gel surface in a regular grid. With nothing touching they sit at rest
(``background`` shows them there). Under a press the gel's nearly incompressible elastomer, bonded to a rigid
backing, is pushed sideways out of the indent and the surface stretches around the indenter, so the dots move
away from the contact: each dot moves by ``-marker_flow * thickness * grad(indentation)``, the gradient taken
on the indentation smoothed over ``marker_smoothing`` (an elastic layer spreads motion beyond the contact
edge). ``decorate`` draws the moved dots onto the simulator's images.

By default (``markers: null``) the markers are drawn only over the procedural background: a real frame
(``background_image``, or a calibration's background) shows the gel as recorded, with its own markers or none.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tnf.registry import FROM_YAML, yaml_defaults
from tnf.sensors import Sensor, SensorConfig

CONF = Path(__file__).parent / "conf"
"""This package's YAML options (``tnf.conf`` entry point): the sensor's values are there."""


class GelSight(Sensor):
    """GelSight Mini-like: 320x240 landscape, flat 18.6x14.3 mm gel, four edge LEDs, moving marker grid."""

    name = "gelsight"

    @dataclass
    @yaml_defaults("sensor/gelsight", conf=CONF)
    class Config(SensorConfig):
        """The GelSight's values: ``conf/sensor/gelsight.yaml`` in this package."""

        markers: bool | None = FROM_YAML
        """Draw the printed marker grid: true or false; null draws it only over the procedural background, not
        over a real frame (``background_image`` or a calibration's background)."""
        marker_spacing: float = FROM_YAML
        """Distance between neighbouring markers, metres (the grid is centred on the gel)."""
        marker_radius: float = FROM_YAML
        """Radius of a printed marker dot, metres."""
        marker_darkness: float = FROM_YAML
        """Fraction of light a marker blocks, in [0, 1] (1 = black)."""
        marker_flow: float = FROM_YAML
        """Lateral marker motion per unit of indentation slope, in units of ``thickness`` (dimensionless)."""
        marker_smoothing: float = FROM_YAML
        """Gaussian smoothing of the indentation before its slope drives the markers, metres (std dev)."""

        def validate(self) -> None:
            super().validate()
            for name in ("marker_spacing", "marker_radius"):
                if getattr(self, name) <= 0:
                    raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
            if 2 * self.marker_radius >= self.marker_spacing:
                raise ValueError(
                    f"marker_radius must be below half of marker_spacing, got {self.marker_radius} and "
                    f"{self.marker_spacing}"
                )
            if not 0.0 <= self.marker_darkness <= 1.0:
                raise ValueError(f"marker_darkness must be in [0, 1], got {self.marker_darkness}")
            if self.marker_flow < 0 or self.marker_smoothing < 0:
                raise ValueError(
                    f"marker_flow and marker_smoothing must be >= 0, got {self.marker_flow}, {self.marker_smoothing}"
                )

    def __init__(self, cfg: Config):
        super().__init__(cfg)
        # Cached by decorate: the marker-free background at background_seed (float32 [H, W, 3]) and the light
        # the markers at rest let through ([H, W]).
        self._clean: np.ndarray | None = None
        self._rest: np.ndarray | None = None

    # -- markers --------------------------------------------------------------------------------------
    @property
    def draws_markers(self) -> bool:
        """Whether the marker grid is drawn: ``markers`` when set, else only over the procedural background."""
        if self.cfg.markers is not None:
            return bool(self.cfg.markers)
        return self.cfg.calibration is None and not self.cfg.background_image

    @property
    def decorates(self) -> bool:
        """True when the markers are drawn (the simulator then calls ``decorate``)."""
        return self.draws_markers

    def marker_rest_positions(self) -> np.ndarray:
        """Rest positions of the markers ``[M, 2]`` = sensor-frame ``(x, y)``, metres, row-major from top left."""
        c = self.cfg
        nx = max(1, int(math.floor(c.gel_width / c.marker_spacing + 1e-9)))
        ny = max(1, int(math.floor(c.gel_height / c.marker_spacing + 1e-9)))
        xs = (np.arange(nx) - (nx - 1) / 2) * c.marker_spacing
        ys = -(np.arange(ny) - (ny - 1) / 2) * c.marker_spacing
        x, y = np.meshgrid(xs, ys)
        return np.stack([x.ravel(), y.ravel()], axis=-1).astype(np.float32)

    def _to_pixels(self, xy: np.ndarray) -> np.ndarray:
        """Sensor-frame ``(x, y)`` metres ``[..., 2]`` -> continuous pixel ``(col, row)`` (pixel centres at k)."""
        fx, fy, cx, cy = self.intrinsics()
        d = self.cfg.camera_distance
        col = xy[..., 0] / d * fx + cx - 0.5
        row = -xy[..., 1] / d * fy + cy - 0.5
        return np.stack([col, row], axis=-1)

    def marker_displacement(self, indentation: np.ndarray) -> np.ndarray:
        """In-plane motion of the gel surface under each marker ``[B, M, 2]``, pixels ``(d_col, d_row)``, for
        indentations ``[B, H, W]`` (metres the surface moved toward the camera):
        ``-marker_flow * thickness * grad(indentation smoothed over marker_smoothing)`` at the rest positions.
        """
        from scipy.ndimage import gaussian_filter

        c = self.cfg
        d = np.asarray(indentation, dtype=np.float32)
        if d.ndim == 2:
            d = d[None]
        b, h, w = d.shape
        dx, dy = self.pixel_size()
        # The smoothed field varies over many pixels: average blocks of f x f pixels first (16x less work at
        # the default sizes), then smooth, differentiate and sample it bilinearly at the markers.
        sigma_px = c.marker_smoothing / dx
        f = max(1, min(int(sigma_px // 4), h // 8, w // 8))
        hc, wc = h // f, w // f
        coarse = d[:, : hc * f, : wc * f].reshape(b, hc, f, wc, f).mean(axis=(2, 4))
        if sigma_px > 0:
            coarse = gaussian_filter(coarse, sigma=(0, sigma_px / f, sigma_px / f), mode="nearest")
        # Slopes (m/m) along columns (+x) and rows (-y); moving against the gradient in pixel space is moving
        # away from the indentation's peak. The metric shift k * slope becomes pixels by dividing by dx.
        g_row, g_col = np.gradient(coarse, axis=(1, 2))
        k = c.marker_flow * c.thickness
        field = np.stack([-k * g_col / (f * dx) / dx, -k * g_row / (f * dy) / dy], axis=-1)  # [B, hc, wc, 2]
        rest = self._to_pixels(self.marker_rest_positions().astype(np.float64))  # [M, 2] fine (col, row)
        u = np.clip((rest[:, 0] - (f - 1) / 2) / f, 0, wc - 1)
        v = np.clip((rest[:, 1] - (f - 1) / 2) / f, 0, hc - 1)
        u0 = np.minimum(np.floor(u).astype(int), max(wc - 2, 0))
        v0 = np.minimum(np.floor(v).astype(int), max(hc - 2, 0))
        u1, v1 = np.minimum(u0 + 1, wc - 1), np.minimum(v0 + 1, hc - 1)
        fu, fv = (u - u0)[None, :, None], (v - v0)[None, :, None]
        out = (
            field[:, v0, u0] * (1 - fu) * (1 - fv)
            + field[:, v0, u1] * fu * (1 - fv)
            + field[:, v1, u0] * (1 - fu) * fv
            + field[:, v1, u1] * fu * fv
        )
        return out.astype(np.float32)

    def marker_pixels(self, indentation: np.ndarray | None = None) -> np.ndarray:
        """Marker centres ``[B, M, 2]`` as continuous pixel ``(col, row)``, moved by ``indentation`` ``[B, H, W]``
        (metres toward the camera); ``None`` gives the rest positions ``[1, M, 2]``."""
        rest = self._to_pixels(self.marker_rest_positions().astype(np.float64))  # [M, 2]
        if indentation is None:
            return rest[None].astype(np.float32)
        # Each dot moves with the gel material under it.
        return (rest[None] + self.marker_displacement(indentation)).astype(np.float32)

    def marker_shading(self, centres: np.ndarray) -> np.ndarray:
        """Light transmitted past the markers ``[B, H, W]`` float32 in [1 - marker_darkness, 1] for marker
        centres ``[B, M, 2]`` (pixel ``(col, row)``): anti-aliased discs of ``marker_radius``."""
        c = self.cfg
        dx, dy = self.pixel_size()
        rad = c.marker_radius / dx  # pixels are square
        reach = int(math.ceil(rad + 1.5))
        off = np.arange(-reach, reach + 1)
        oc, orow = np.meshgrid(off, off)
        oc, orow = oc.ravel(), orow.ravel()  # [K]
        centres = np.asarray(centres, dtype=np.float64)
        b = centres.shape[0]
        base_c = np.rint(centres[..., 0])[..., None] + oc  # [B, M, K]
        base_r = np.rint(centres[..., 1])[..., None] + orow
        dist = np.hypot(base_c - centres[..., 0:1], base_r - centres[..., 1:2])
        cover = np.clip(rad + 0.5 - dist, 0.0, 1.0)
        value = (1.0 - c.marker_darkness * cover).astype(np.float32)
        inside = (base_c >= 0) & (base_c < self.width) & (base_r >= 0) & (base_r < self.height) & (cover > 0)
        bi = np.broadcast_to(np.arange(b)[:, None, None], inside.shape)
        out = np.ones((b, self.height, self.width), dtype=np.float32)
        np.minimum.at(out, (bi[inside], base_r[inside].astype(int), base_c[inside].astype(int)), value[inside])
        return out

    # -- images ---------------------------------------------------------------------------------------
    def background(self, seed: int | None = None) -> np.ndarray:
        """The untouched sensor ``[H, W, 3]`` uint8: the base class's background with the markers at rest."""
        img = super().background(seed)
        if not self.draws_markers:
            return img
        shade = self.marker_shading(self.marker_pixels())[0]
        return np.clip(np.rint(img * shade[..., None]), 0, 255).astype(np.uint8)

    def decorate(self, image: np.ndarray, indentation: np.ndarray) -> np.ndarray:
        """Move the markers with the gel: ``image`` ``[B, H, W, 3]`` uint8 (the simulator's render, which starts
        from ``background()`` with the markers at rest) and ``indentation`` ``[B, H, W]`` metres.

        The light the rest markers hid is added back (from the marker-free background at ``background_seed``)
        and the moved markers are drawn over it; where the gel did not move the markers stay where they were.
        """
        if not self.draws_markers:
            return image
        if self._clean is None or self._rest is None:
            self._clean = Sensor.background(self, self.cfg.background_seed).astype(np.float32)
            self._rest = self.marker_shading(self.marker_pixels())[0]
        moved = self.marker_shading(self.marker_pixels(indentation))
        out = (image.astype(np.float32) + self._clean * (1.0 - self._rest)[..., None]) * moved[..., None]
        image[...] = np.clip(np.rint(out), 0, 255).astype(np.uint8)
        return image
