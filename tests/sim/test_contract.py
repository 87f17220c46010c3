"""The in-tree simulator passes the same contract suite as a plugin's simulator."""

from tnf.testing import SimulatorContract


class TestWarpGelContract(SimulatorContract):
    name = "warp_gel"
