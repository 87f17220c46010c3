"""Tactile sensors: the ``Sensor`` base class (the plugin API) and the in-tree sensors (digit, omnitact, gelsight_mini).

In-tree sensors register in ``tnf.registry.SENSORS`` when that registry is first used; build one with
``SENSORS.build(cfg.sensor)``. Importing this package is cheap (numpy only).
"""

from tnf.sensors.base import Light, Sensor, SensorConfig, load_background

__all__ = ["Light", "Sensor", "SensorConfig", "load_background"]
