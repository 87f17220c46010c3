"""The sensor contract suite."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import pytest

from tnf.registry import (
    SENSORS,
    SIMULATORS,
    config_to_dict,
)
from tnf.sensors import Sensor
from tnf.testing.config import compose
from tnf.testing.contracts.base import _ComponentContract


# -- sensors ----------------------------------------------------------------------------------------
class SensorContract(_ComponentContract):
    """A tactile sensor (``tnf.sensors.Sensor`` subclass) works with the config tree and the warp simulator.

    Checks: registration and documented Config fields; config round trip through the registry and
    ``config_to_dict``; the sensor's YAML (``conf/sensor/<name>.yaml``, or a plugin's through ``tnf.conf``)
    composes and builds; camera, gel and shading outputs have the documented shapes and dtypes; the
    background is ``[H, W, 3]`` uint8, the same for the same seed and different for another; a sphere pressed
    with the ``warp_gel`` simulator makes contact and an image that differs from the background, and a press
    that misses leaves the background (plus noise); a mirror symmetry the sensor reports holds in the simulator.
    """

    registry = SENSORS
    simulator: ClassVar[dict[str, Any]] = {"name": "warp_gel"}
    """Simulator config used for the press test."""
    sphere_radius: ClassVar[float] = 0.01
    """Radius of the pressed sphere, metres."""

    @pytest.fixture(scope="class")
    @classmethod
    def sensor(cls) -> Any:
        """The sensor under test (built once per test class)."""
        return SENSORS.build(cls.spec())

    @classmethod
    def press_force(cls, sensor: Any) -> float:
        """Target force of the press test, newtons: a tenth of the way into the sensor's force range."""
        lo, hi = sensor.cfg.force_range
        return float(lo + 0.1 * (hi - lo))

    def test_is_a_sensor_named_as_registered(self, sensor):

        assert isinstance(sensor, Sensor)
        assert sensor.name == self.name, "set the class attribute `name` to the registry name"
        assert sensor.describe() == {"name": self.name, "config": config_to_dict(sensor.cfg)}

    def test_yaml_composes_and_builds(self):
        cfg = compose("touch", [f"sensor={self.name}"])
        built = SENSORS.build(cfg.sensor)
        assert built.name == self.name

    def test_camera_and_gel_shapes(self, sensor):
        h, w = sensor.height, sensor.width
        fx, fy, cx, cy = sensor.intrinsics()
        assert fx > 0 and fy > 0 and 0 < cx < w and 0 < cy < h
        x, y = sensor.gel_grid()
        assert x.shape == y.shape == (h, w) and x.dtype == y.dtype == np.float32
        assert x[0, 0] < x[0, -1] and y[0, 0] > y[-1, 0], "columns grow with +x, rows with -y"
        surf = sensor.gel_surface()
        assert surf.shape == (h, w) and surf.dtype == np.float32
        assert np.isfinite(surf).all() and surf.min() >= 0
        mask = sensor.gel_mask()
        assert mask.shape == (h, w) and mask.dtype == bool and mask.mean() > 0.25
        pts = sensor.gel_points()
        assert pts.shape == (h, w, 3) and pts.dtype == np.float32 and (pts[..., 2] < 0).all()
        n = sensor.surface_normals(surf)
        assert n.shape == (h, w, 3) and np.allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-4) and (n[..., 2] > 0).all()
        lit = sensor.shade(pts, n)
        assert lit.shape == (h, w, 3) and lit.dtype == np.float32 and np.isfinite(lit).all() and lit.min() >= 0

    def test_background_shape_dtype_determinism(self, sensor):
        bg = sensor.background()
        assert bg.shape == (sensor.height, sensor.width, 3) and bg.dtype == np.uint8
        assert np.array_equal(bg, sensor.background()), "the background must be deterministic"
        assert 10 < bg.mean() < 245, "a background should be neither black nor white"
        if sensor.cfg.background_image or sensor.cfg.calibration:
            return  # a photo does not vary with the seed
        b0, b1 = sensor.background(0), sensor.background(1)
        assert np.array_equal(b0, sensor.background(0))
        assert np.abs(b0.astype(np.int16) - b1).mean() > 1, "another seed should give another background"

    @pytest.fixture(scope="class")
    @classmethod
    def pressed(cls, sensor) -> tuple[Any, Any, float]:
        """``(simulator, TouchBatch, target force)`` of three presses on a sphere (the third one misses)."""
        import trimesh

        r = cls.sphere_radius
        sim = SIMULATORS.build(cls.simulator, sensor=sensor, device="cpu")
        sphere = trimesh.creation.icosphere(subdivisions=3, radius=r)
        # Camera above the sphere looking down (-z): centred, off-centre by a third of the sphere's radius,
        # and one beside the sphere that misses it.
        poses = np.repeat(np.eye(4)[None], 3, 0)
        poses[:, 2, 3] = r + sensor.cfg.camera_distance + 0.01
        poses[1, 0, 3] = r / 3
        poses[2, 0, 3] = 10 * r
        force = cls.press_force(sensor)
        return sim, sim.press(sphere, poses, force, seed=0), force

    def test_press_on_sphere_makes_contact(self, sensor, pressed):
        _, out, force = pressed
        h, w = sensor.height, sensor.width
        assert out.images.shape == (3, h, w, 3) and out.images.dtype == np.uint8
        assert out.indentation.shape == (3, h, w) and out.indentation.dtype == np.float32
        assert out.contact.shape == (3, h, w) and out.contact.dtype == bool
        assert out.hit.tolist() == [True, True, False]
        for i in (0, 1):
            assert out.contact[i].any() and out.indentation[i].max() > 0
            assert 0 < out.force[i] <= force * 1.05
            assert 0 < out.penetration[i] <= sensor.cfg.max_penetration * 1.001
        assert not out.contact[2].any()

    def test_press_changes_the_image_and_a_miss_does_not(self, sensor, pressed):
        _, out, _ = pressed
        bg = sensor.background().astype(np.float32)
        for i in (0, 1):
            diff = np.abs(out.images[i].astype(np.float32) - bg).mean(-1)
            assert diff[out.contact[i]].mean() > 8, "the contact should show in the image"
        miss = np.abs(out.images[2].astype(np.float32) - bg)
        assert miss.mean() < 3 * max(sensor.cfg.noise_std, 1.0), "no contact should give the background plus noise"

    def test_mirror_symmetry_holds_in_the_simulator(self, sensor, pressed):
        """Where ``mirror_channels`` reports a symmetry (``data.augment=[mirror]`` relies on it), the press
        off-centre by +r/3 is the press at -r/3 flipped left-right with its channels reordered."""
        order = sensor.mirror_channels()
        if order is None:
            pytest.skip(f"{self.name} has no mirror symmetry")
        import trimesh

        sim, out, force = pressed
        r = self.sphere_radius
        pose = np.eye(4)
        pose[2, 3] = r + sensor.cfg.camera_distance + 0.01
        pose[0, 3] = -r / 3
        sphere = trimesh.creation.icosphere(subdivisions=3, radius=r)
        mirrored = sim.press(sphere, pose[None], force, seed=1)
        bg = sensor.background().astype(np.float32)
        diff = out.images[1].astype(np.float32) - bg
        diff_m = mirrored.images[0].astype(np.float32) - bg
        region = out.contact[1][:, ::-1] | mirrored.contact[0]
        energy = np.abs(diff_m)[region].mean()
        err = np.abs(diff[:, ::-1][..., list(order)] - diff_m)[region].mean()
        assert err < 0.1 * energy + 2 * sensor.cfg.noise_std, (
            f"mirror_channels() says {order}, but the mirrored press differs by {err:.1f} (imprint {energy:.1f})"
        )
