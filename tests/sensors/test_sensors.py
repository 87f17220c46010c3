from pathlib import Path

import numpy as np
import pytest

from tnf.errors import TnfError
from tnf.registry import SENSORS
from tnf.sensors import Sensor
from tnf.testing import compose

ASSET = Path(__file__).resolve().parents[1] / "assets" / "bg_digit_240_320.jpg"


@pytest.mark.parametrize("name", ["digit", "omnitact", "gelsight_mini"])
def test_yaml_matches_defaults_and_validates(name):
    cfg = compose("touch", [f"sensor={name}"])
    sensor = SENSORS.build(cfg.sensor)
    assert isinstance(sensor, Sensor) and sensor.name == name
    # The Config's defaults are the YAML's values: building from a bare name gives the same sensor.
    assert sensor.describe() == SENSORS.build(name).describe()


def test_digit_figures():
    s = SENSORS.build("digit")
    assert (s.width, s.height) == (240, 320)
    fx, fy, cx, cy = s.intrinsics()
    assert fx == fy and (cx, cy) == (120, 160)
    # 60 deg vertical fov at 22 mm: the image spans 2 * 22 * tan(30 deg) = 25.4 mm of gel vertically.
    x, y = s.gel_grid()
    assert y.max() - y.min() == pytest.approx(0.0254, rel=0.01)
    h = s.gel_surface()
    assert h.max() == pytest.approx(0.005, rel=0.02) and h.min() >= 0
    assert len(s.cfg.lights) == 3


@pytest.mark.parametrize(
    "override, match",
    [({"young_modulus": -1.0}, "young_modulus"), ({"poisson_ratio": 0.5}, "poisson_ratio"), ({"fovv": 3}, "fovv")],
)
def test_bad_config_is_one_line_error(override, match):
    with pytest.raises(TnfError, match=match):
        SENSORS.build({"name": "digit", **override})


def test_backgrounds_differ_by_sensor_and_seed():
    d = SENSORS.build("digit")
    o = SENSORS.build("omnitact")
    b0, b1 = d.background(0), d.background(1)
    assert b0.shape == (320, 240, 3) and b0.dtype == np.uint8
    assert np.array_equal(b0, d.background(0))
    assert np.abs(b0.astype(int) - b1).mean() > 3
    # Digit: red glow top right, green top left, blue at the bottom.
    assert b0[:100, 160:, 0].mean() > b0[:100, :80, 0].mean()
    assert b0[:100, :80, 1].mean() > b0[:100, 160:, 1].mean()
    assert b0[240:, :, 2].mean() > b0[:80, :, 2].mean()
    assert o.background(0).shape == (240, 240, 3)
    assert np.abs(o.background(0)[60:180, 60:180].mean((0, 1)) - b0[120:240, 60:180].mean((0, 1))).max() > 10


def test_background_from_photo_and_bad_file(tmp_path):
    s = SENSORS.build({"name": "digit", "background_image": str(ASSET)})
    bg = s.background()
    assert bg.shape == (320, 240, 3) and 60 < bg.mean() < 160
    small = SENSORS.build({"name": "digit", "width": 120, "height": 160, "background_image": str(ASSET)})
    assert small.background().shape == (160, 120, 3)
    bad = tmp_path / "bg.png"
    bad.write_text("not an image")
    with pytest.raises(TnfError, match="not a readable image"):
        SENSORS.build({"name": "digit", "background_image": str(bad)}).background()
    with pytest.raises(TnfError, match="not found"):
        SENSORS.build({"name": "digit", "background_image": str(tmp_path / "missing.png")}).background()


def test_shading_brighter_toward_light():
    s = SENSORS.build({"name": "digit", "sag": 0.0})
    h = np.zeros((s.height, s.width), np.float32)
    flat = s.shade(s.gel_points(h), s.surface_normals(h))
    # A slope facing the red LED (upper right) gets more red than the flat gel.
    x, y = s.gel_grid()
    # Outward height growing toward the red LED tilts the camera-facing normal toward it.
    tilt = (0.2 * (x * 0.866 + y * 0.5)).astype(np.float32)
    tilted = s.shade(s.gel_points(h), s.surface_normals(tilt))
    assert tilted[..., 0].mean() > flat[..., 0].mean()


def test_mirror_symmetry_follows_the_lights_and_gel():
    # The Digit's red and green LEDs are mirror images (30 and 150 degrees), its blue one on the axis.
    assert SENSORS.build("digit").mirror_channels() == (1, 0, 2)
    # Moving the green LED off its mirror position breaks the symmetry.
    lights = [
        {"position": [0.011258, 0.0065, -0.02], "color": [1.0, 0.0, 0.0], "intensity": 1.0},
        {"position": [-0.009, 0.0065, -0.02], "color": [0.0, 1.0, 0.0], "intensity": 1.0},
        {"position": [0.0, -0.013, -0.02], "color": [0.0, 0.0, 1.0], "intensity": 1.0},
    ]
    assert SENSORS.build({"name": "digit", "lights": lights}).mirror_channels() is None
    # A light on the axis keeps it with every channel in place.
    axis = [{"position": [0.0, 0.01, -0.02], "color": [1.0, 0.5, 0.2], "intensity": 1.0}]
    assert SENSORS.build({"name": "digit", "lights": axis}).mirror_channels() == (0, 1, 2)
    assert SENSORS.build("omnitact").mirror_channels() is None

    class Marked(type(SENSORS.build("digit"))):  # markers drawn on the image: no symmetry is assumed
        def decorate(self, image, indentation):
            return image

    assert Marked(Marked.Config()).mirror_channels() is None
