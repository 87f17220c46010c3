"""Contract test suites: what every sensor, simulator, generator, scene and object source (in-tree or from a
plugin) must satisfy.

Subclass a suite in a test module and name the component; pytest collects the inherited tests::

    from tnf.testing import SensorContract

    class TestGelSightContract(SensorContract):
        name = "gelsight"

Each suite has class attributes a subclass may set (``params``: config overrides, e.g. to make a generator
tiny) and fixtures it may override (``sensor``, ``simulator``, ``generator``, ``scene``, ``source``) when a
component needs more than its registry name to be built. The tests use real components: real warp presses,
real training steps, real renders, at tiny sizes so that a suite runs in seconds on a CPU.
"""

from tnf.testing.contracts.base import undocumented_fields
from tnf.testing.contracts.generator import GeneratorContract, random_batch
from tnf.testing.contracts.objects import ObjectSourceContract
from tnf.testing.contracts.scene import SceneContract
from tnf.testing.contracts.sensor import SensorContract
from tnf.testing.contracts.simulator import SimulatorContract, sphere_gaps

__all__ = [
    "GeneratorContract",
    "ObjectSourceContract",
    "SceneContract",
    "SensorContract",
    "SimulatorContract",
    "random_batch",
    "sphere_gaps",
    "undocumented_fields",
]
