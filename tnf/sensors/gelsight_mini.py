"""GelSight Mini: a flat gel lit from its edges, seen by a 4:3 camera; geometry from a real recording.

The image geometry is that of Taxim's GelSight Mini calibration recording at half its resolution: 640x480
frames at 0.0295 mm per pixel, here 320x240 at 0.059 mm per pixel (18.9 x 14.2 mm of gel). The lights are a
guess (four coloured LEDs at the gel's edges); ``tnf calibrate`` replaces them, the blur, the noise and the
background with what it measures on real presses (``sensor.calibration=...``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from tnf.sensors.base import Light, Sensor, SensorConfig

CAMERA_DISTANCE = 0.015
"""Camera to the gel, metres."""
MM_PER_PIXEL = 0.059
"""Gel size of one pixel at 320x240, millimetres (twice the recording's 0.0295 at 640x480)."""


def _fov(height: int = 240) -> float:
    """Vertical field of view (degrees) that gives ``MM_PER_PIXEL`` at ``CAMERA_DISTANCE`` for 240 rows."""
    return math.degrees(2 * math.atan(0.5 * height * MM_PER_PIXEL * 1e-3 / CAMERA_DISTANCE))


def _edge_lights() -> list[Light]:
    z = -0.012
    return [
        Light((0.0095, 0.0, z), (1.0, 0.15, 0.15), 1.0),  # red, right edge
        Light((-0.0095, 0.0, z), (0.15, 0.3, 1.0), 1.0),  # blue, left edge
        Light((0.0, -0.0071, z), (0.15, 1.0, 0.3), 1.0),  # green, bottom edge
        Light((0.0, 0.0071, z), (1.0, 0.9, 0.8), 0.5),  # dim white, top edge
    ]


class GelSightMini(Sensor):
    """GelSight Mini: 320x240 landscape, flat 19 x 14.2 mm gel, edge LEDs; calibrate it from real presses."""

    name = "gelsight_mini"

    @dataclass
    class Config(SensorConfig):
        width: int = 320
        """Image width W, pixels (landscape)."""
        height: int = 240
        """Image height H, pixels."""
        fov: float = field(default_factory=_fov)
        """Vertical field of view, degrees: 0.059 mm per pixel on the gel at ``camera_distance`` (50.5)."""
        camera_distance: float = CAMERA_DISTANCE
        """Camera to the gel surface, metres."""
        gel_width: float = 0.0190
        """Gel size along image x, metres (the whole image sees gel)."""
        gel_height: float = 0.0143
        """Gel size along image y, metres."""
        sag: float = 0.0
        """The Mini's gel is flat."""
        thickness: float = 0.003
        """Elastomer thickness over the rigid backing, metres."""
        young_modulus: float = 2.0e5
        """Young's modulus of the soft silicone, pascals."""
        poisson_ratio: float = 0.49
        """Poisson ratio (nearly incompressible)."""
        max_penetration: float = 0.0025
        """Deepest indentation simulated, metres."""
        force_range: tuple[float, float] = (0.0, 15.0)
        """Usable normal force (min, max), newtons."""
        lights: list[Light] = field(default_factory=_edge_lights)
        """Uncalibrated guess: red right, blue left, green bottom, dim white top, grazing from the edges."""
        specular: float = 0.1
        """Weight of specular highlights (matte coating)."""
        contrast: float = 200.0
        """Gain from shading difference to 8-bit values."""
        blur_sigma: float = 1.0
        """Blur of the difference image, pixels."""
        noise_std: float = 1.0
        """Pixel noise, 8-bit units."""
