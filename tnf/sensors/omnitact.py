"""OmniTact: a tip camera looking into a curved, dome-like gel lit by coloured lights around the tip."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from tnf.sensors.base import Light, Sensor, SensorConfig


def _omnitact_lights() -> list[Light]:
    out = []
    for angle, color in ((90.0, (1.0, 0.75, 0.35)), (210.0, (0.25, 0.9, 1.0)), (330.0, (0.95, 0.3, 0.85))):
        a = math.radians(angle)
        out.append(Light((0.011 * math.cos(a), 0.011 * math.sin(a), -0.009), color, 0.9))
    return out


class OmniTact(Sensor):
    """OmniTact: tip camera (70 deg fov) inside a domed gel, amber/cyan/magenta lights."""

    name = "omnitact"

    @dataclass
    class Config(SensorConfig):
        width: int = 240
        """Image width W, pixels."""
        height: int = 240
        """Image height H, pixels."""
        fov: float = 70.0
        """Vertical field of view of the tip camera, degrees."""
        camera_distance: float = 0.012
        """Camera to the dome's base plane, metres."""
        gel_width: float = 0.017
        """Diameter of the dome's base along x, metres."""
        gel_height: float = 0.017
        """Diameter of the dome's base along y, metres."""
        sag: float = 0.006
        """Height of the dome above its base, metres."""
        thickness: float = 0.003
        """Elastomer thickness, metres."""
        young_modulus: float = 5.0e5
        """Young's modulus of the (stiffer) silicone, pascals."""
        specular: float = 0.35
        """Weight of specular highlights (the dome's coating is glossier)."""
        lights: list[Light] = field(default_factory=_omnitact_lights)
        """Amber, cyan and magenta lights around the camera."""

    def gel_surface(self) -> np.ndarray:
        """A spherical cap: ``sag`` high at the centre, 0 on the ellipse inscribed in the gel's base."""
        c = self.cfg
        x, y = self.gel_grid()
        a = min(c.gel_width, c.gel_height) / 2
        r2 = (x * a / (c.gel_width / 2)) ** 2 + (y * a / (c.gel_height / 2)) ** 2
        radius = (a * a + c.sag * c.sag) / (2 * c.sag) if c.sag > 0 else np.inf
        if not np.isfinite(radius):
            return np.zeros_like(x)
        h = np.sqrt(np.clip(radius * radius - r2, 0, None)) - (radius - c.sag)
        return np.clip(h, 0, None).astype(np.float32)

    def gel_mask(self) -> np.ndarray:
        """Pixels inside the dome's elliptical base."""
        c = self.cfg
        x, y = self.gel_grid()
        return (x / (c.gel_width / 2)) ** 2 + (y / (c.gel_height / 2)) ** 2 <= 1.0
