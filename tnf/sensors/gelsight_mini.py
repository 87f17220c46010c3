"""GelSight Mini: a flat gel lit from its edges, seen by a 4:3 camera; geometry from a real recording.

The image geometry is that of Taxim's GelSight Mini calibration recording at half its resolution: 640x480
frames at 0.0295 mm per pixel, here 320x240 at 0.059 mm per pixel (18.9 x 14.2 mm of gel). The lights are a
guess (four coloured LEDs at the gel's edges); ``tnf calibrate`` replaces them, the blur, the noise and the
background with what it measures on real presses (``sensor.calibration=...``).
"""

from __future__ import annotations

from dataclasses import dataclass

from tnf.registry import yaml_defaults
from tnf.sensors.base import Sensor, SensorConfig


class GelSightMini(Sensor):
    """GelSight Mini: 320x240 landscape, flat 19 x 14.2 mm gel, edge LEDs; calibrate it from real presses."""

    name = "gelsight_mini"

    @dataclass
    @yaml_defaults("sensor/gelsight_mini")
    class Config(SensorConfig):
        """The GelSight Mini's values: ``conf/sensor/gelsight_mini.yaml``."""
