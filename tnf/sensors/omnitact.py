"""OmniTact: a tip camera looking into a curved, dome-like gel lit by coloured lights around the tip."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tnf.registry import yaml_defaults
from tnf.sensors.base import Sensor, SensorConfig


class OmniTact(Sensor):
    """OmniTact: tip camera (70 deg fov) inside a domed gel, amber/cyan/magenta lights."""

    name = "omnitact"

    @dataclass
    @yaml_defaults("sensor/omnitact")
    class Config(SensorConfig):
        """OmniTact's values: ``conf/sensor/omnitact.yaml``."""

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
