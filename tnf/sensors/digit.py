"""DIGIT: a compact vision-based tactile sensor with a convex gel lit by red, green and blue LEDs."""

from __future__ import annotations

from dataclasses import dataclass

from tnf.registry import yaml_defaults
from tnf.sensors.base import Sensor, SensorConfig


class Digit(Sensor):
    """DIGIT: 240x320 portrait camera behind a 20x30 mm convex gel, red/green/blue LEDs around its edge."""

    name = "digit"

    @dataclass
    @yaml_defaults("sensor/digit")
    class Config(SensorConfig):
        """The DIGIT's values: ``conf/sensor/digit.yaml``."""
