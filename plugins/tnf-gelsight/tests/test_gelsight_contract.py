"""The GelSight sensor meets tnf's sensor contract (the same suite the in-tree Digit and OmniTact pass)."""

from tnf.testing import SensorContract


class TestGelSightContract(SensorContract):
    name = "gelsight"
