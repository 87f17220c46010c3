"""tnf: tactile sensor data from camera images.

A scene representation fitted to an object's camera images renders RGB-D from any pose; a conditional
generator maps that RGB-D plus a sensor's background image to the tactile image the sensor would show.
Importing ``tnf`` is cheap: components and plugins load at first lookup in a registry.
"""

__version__ = "0.1.0"

from tnf.errors import TnfError

__all__ = ["TnfError", "__version__"]
