"""DIGIT: a compact vision-based tactile sensor with a convex gel lit by red, green and blue LEDs."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from tnf.sensors.base import Light, Sensor, SensorConfig


def _ring_light(angle_deg: float, color: tuple[float, float, float], radius: float = 0.013, z: float = -0.020) -> Light:
    a = math.radians(angle_deg)
    return Light((radius * math.cos(a), radius * math.sin(a), z), color, 1.0)


def _digit_lights() -> list[Light]:
    return [
        _ring_light(30.0, (1.0, 0.0, 0.0)),
        _ring_light(150.0, (0.0, 1.0, 0.0)),
        _ring_light(270.0, (0.0, 0.0, 1.0)),
    ]


class Digit(Sensor):
    """DIGIT: 240x320 portrait camera behind a 20x30 mm convex gel, red/green/blue LEDs around its edge."""

    name = "digit"

    @dataclass
    class Config(SensorConfig):
        width: int = 240
        """Image width W, pixels."""
        height: int = 320
        """Image height H, pixels (portrait)."""
        fov: float = 60.0
        """Vertical field of view, degrees."""
        camera_distance: float = 0.022
        """Camera to the gel's rim plane, metres."""
        gel_width: float = 0.020
        """Gel width, metres."""
        gel_height: float = 0.030
        """Gel height, metres."""
        sag: float = 0.005
        """Convex bulge of the gel's centre beyond its rim, metres."""
        lights: list[Light] = field(default_factory=_digit_lights)
        """Red, green and blue LEDs at 30, 150 and 270 degrees around the gel's edge."""
