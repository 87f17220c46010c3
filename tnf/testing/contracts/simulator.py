"""The simulator contract suite."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import pytest

from tnf.errors import TnfError
from tnf.registry import (
    SENSORS,
    SIMULATORS,
)
from tnf.sim.base import Simulator
from tnf.testing.config import compose
from tnf.testing.contracts.base import _ComponentContract


# -- simulators -------------------------------------------------------------------------------------
def sphere_gaps(sensor: Any, radius: float, centre_xy: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """``[H, W]`` gaps (metres, along the sensor's -z) from the undeformed gel to a sphere of ``radius`` metres
    whose top touches the gel's lowest point; inf where the pixel's ray misses the sphere."""
    pts = sensor.gel_points().astype(np.float64)
    r2 = (pts[..., 0] - centre_xy[0]) ** 2 + (pts[..., 1] - centre_xy[1]) ** 2
    cz = pts[..., 2].min() - radius  # the sphere's top at the gel's lowest point
    top = cz + np.sqrt(np.maximum(radius**2 - r2, 0.0))
    gaps = np.where(r2 < radius**2, pts[..., 2] - top, np.inf)
    return (gaps - np.nanmin(gaps[np.isfinite(gaps)])).astype(np.float32)


class SimulatorContract(_ComponentContract):
    """A tactile simulator (``tnf.sim.base.Simulator`` subclass) presses a sensor and returns a ``TouchBatch``.

    Checks: registration and documented Config; config round trip; the YAML (``conf/simulator/<name>.yaml``,
    or a plugin's) composes and builds; the background is the sensor's ``[H, W, 3]`` uint8; three presses on a
    sphere (centred, off-centre, beside it) give every ``TouchBatch`` field with its shape and dtype, contact
    for the first two and none for the third (no contact point, no advance); the same seed gives the same
    images; a larger force goes deeper over a larger area; ``press_heights`` to a penetration indents that deep,
    and to a force reaches it; a penetration past the sensor's ``max_penetration`` is a one-line TnfError naming
    the setting.
    """

    registry = SIMULATORS
    sensor_spec: ClassVar[dict[str, Any]] = {"name": "digit", "width": 60, "height": 80}
    """The sensor the simulator is built for (small, to keep the suite fast)."""
    sphere_radius: ClassVar[float] = 0.01
    """Radius of the pressed sphere, metres."""

    @pytest.fixture(scope="class")
    @classmethod
    def simulator(cls) -> Any:
        """The simulator under test on the CPU (built once per test class)."""
        sensor = SENSORS.build(cls.sensor_spec)
        return SIMULATORS.build(cls.spec(), sensor=sensor, device="cpu")

    @classmethod
    def forces(cls, sensor: Any) -> tuple[float, float]:
        """A light and a firm press, newtons: a tenth and a third of the way into the sensor's force range."""
        lo, hi = sensor.cfg.force_range
        return float(lo + 0.1 * (hi - lo)), float(lo + 0.33 * (hi - lo))

    @classmethod
    def poses(cls, sensor: Any) -> np.ndarray:
        """``[3, 4, 4]`` start poses above the sphere looking down: centred, off-centre by r/3, and beside it."""
        r = cls.sphere_radius
        poses = np.repeat(np.eye(4)[None], 3, 0)
        poses[:, 2, 3] = r + sensor.cfg.camera_distance + 0.01
        poses[1, 0, 3] = r / 3
        poses[2, 0, 3] = 10 * r
        return poses

    @pytest.fixture(scope="class")
    @classmethod
    def pressed(cls, simulator) -> Any:
        """The ``TouchBatch`` of the three presses at the light force."""
        import trimesh

        sphere = trimesh.creation.icosphere(subdivisions=3, radius=cls.sphere_radius)
        return simulator.press(sphere, cls.poses(simulator.sensor), cls.forces(simulator.sensor)[0], seed=0)

    def test_is_a_simulator(self, simulator):

        assert isinstance(simulator, Simulator)
        s = simulator.sensor
        assert simulator.background.shape == (s.height, s.width, 3) and simulator.background.dtype == np.uint8

    def test_yaml_composes_and_builds(self):
        cfg = compose("touch", [f"simulator={self.name}"])
        assert cfg.simulator.name == self.name
        built = SIMULATORS.build(cfg.simulator, sensor=SENSORS.build(self.sensor_spec), device="cpu")
        assert type(built) is SIMULATORS.get(self.name)

    def test_touch_batch_fields(self, simulator, pressed):
        h, w = simulator.sensor.height, simulator.sensor.width
        expected = {
            "images": ((3, h, w, 3), np.uint8),
            "indentation": ((3, h, w), np.float32),
            "contact": ((3, h, w), np.bool_),
            "force": ((3,), np.float32),
            "penetration": ((3,), np.float32),
            "hit": ((3,), np.bool_),
            "advance": ((3,), np.float32),
            "contact_point": ((3, 3), None),
            "contact_c2w": ((3, 4, 4), None),
        }
        for field, (shape, dtype) in expected.items():
            value = getattr(pressed, field)
            assert isinstance(value, np.ndarray) and value.shape == shape, f"{field}: {getattr(value, 'shape', None)}"
            if dtype is not None:
                assert value.dtype == dtype, f"{field}: {value.dtype}, expected {np.dtype(dtype)}"

    def test_press_on_sphere_makes_contact_and_a_miss_does_not(self, simulator, pressed):
        force = self.forces(simulator.sensor)[0]
        assert pressed.hit.tolist() == [True, True, False]
        for i in (0, 1):
            assert pressed.contact[i].any() and pressed.indentation[i].max() > 0
            assert 0 < pressed.force[i] <= force * 1.05
            assert 0 < pressed.penetration[i] <= simulator.sensor.cfg.max_penetration * 1.001
            assert np.isfinite(pressed.advance[i]) and np.isfinite(pressed.contact_point[i]).all()
        assert not pressed.contact[2].any() and not np.isfinite(pressed.advance[2])
        assert np.isnan(pressed.contact_point[2]).all()

    def test_same_seed_same_images(self, simulator, pressed):
        import trimesh

        sphere = trimesh.creation.icosphere(subdivisions=3, radius=self.sphere_radius)
        again = simulator.press(sphere, self.poses(simulator.sensor), self.forces(simulator.sensor)[0], seed=0)
        assert np.array_equal(again.images, pressed.images)
        assert np.array_equal(again.contact, pressed.contact)

    def test_more_force_goes_deeper_over_a_larger_area(self, simulator, pressed):
        import trimesh

        sphere = trimesh.creation.icosphere(subdivisions=3, radius=self.sphere_radius)
        firm = simulator.press(sphere, self.poses(simulator.sensor)[:1], self.forces(simulator.sensor)[1], seed=0)
        assert firm.penetration[0] > pressed.penetration[0]
        assert firm.contact[0].sum() > pressed.contact[0].sum()
        assert firm.force[0] > pressed.force[0]

    def test_press_heights_to_a_penetration_and_to_a_force(self, simulator):
        s = simulator.sensor
        gaps = sphere_gaps(s, self.sphere_radius)[None]
        depth = 0.3 * s.cfg.max_penetration
        deep = simulator.press_heights(gaps, penetration=depth)
        assert deep.hit.tolist() == [True] and deep.contact[0].any()
        assert np.isclose(deep.indentation[0].max(), depth, rtol=0.05), (deep.indentation[0].max(), depth)
        assert deep.force[0] > 0
        force = self.forces(s)[0]
        pressed = simulator.press_heights(gaps, force=force)
        assert np.isclose(pressed.force[0], force, rtol=0.05), (pressed.force[0], force)
        with pytest.raises(TnfError):
            simulator.press_heights(gaps[:, :-1], force=force)  # not the sensor's pixel grid

    def test_press_heights_past_max_penetration_is_refused(self, simulator):
        s = simulator.sensor
        gaps = np.repeat(sphere_gaps(s, self.sphere_radius)[None], 2, 0)
        limit = s.cfg.max_penetration
        at_limit = simulator.press_heights(gaps[:1], penetration=limit)
        assert at_limit.penetration[0] == pytest.approx(limit, rel=1e-3)
        with pytest.raises(TnfError, match="max_penetration") as e:
            simulator.press_heights(gaps, penetration=[0.5 * limit, 1.5 * limit])
        assert "\n" not in str(e.value)
