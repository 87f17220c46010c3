"""The in-tree sensors pass the same contract suite as plugin sensors."""

from tnf.testing import SensorContract


class TestDigitContract(SensorContract):
    name = "digit"


class TestOmniTactContract(SensorContract):
    name = "omnitact"


class TestGelSightMiniContract(SensorContract):
    name = "gelsight_mini"
