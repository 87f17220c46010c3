"""Generated touches of real presses: the indenter rendered as RGB-D at each press's pose, a trained
generator's images of them at the sensor's size, and their scores against the real frames."""

import dataclasses

import numpy as np
import pytest

from tests.real.tiny_generator import train_tiny_generator
from tnf.data.render import Framing
from tnf.errors import TnfError
from tnf.real import report
from tnf.real.generated import (
    checkpoint_framing,
    crop_pixels,
    generate_presses,
    press_rgbd,
)
from tnf.real.presses import at_sensor_size
from tnf.registry import SENSORS

PRESSES = [19, 0, 3, 6]  # depths 0.27, 0.36, 0.75 and 0.92 mm


@pytest.fixture(scope="module")
def sensor():
    return SENSORS.build({"name": "gelsight_mini", "width": 80, "height": 60})


@pytest.fixture(scope="module")
def sp(taxim_presses, sensor):
    return at_sensor_size(taxim_presses, sensor, PRESSES)


@pytest.fixture(scope="module")
def radius(taxim_presses):
    return taxim_presses.radius_mm * 1e-3


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return train_tiny_generator(tmp_path_factory.mktemp("tiny") / "tnf-data")


def test_press_rgbd_puts_the_nearest_point_under_each_press_centre(sensor, sp, radius):
    # The recording's presses sit near the middle: move two of them to the corners of the gel.
    spread = dataclasses.replace(sp, centers=np.array([[12.0, 9.0], [66.0, 50.0], [40.0, 30.0], [20.0, 45.0]]))
    v = press_rgbd(sensor, spread, radius)
    assert v.rgb.shape == (4, 128, 128, 3) and v.rgb.dtype == np.uint8
    assert v.depth.shape == (4, 128, 128) and v.depth.dtype == np.float16
    assert v.c2w.shape == (4, 4, 4) and v.pixels.shape == (4, 2)
    for i in range(4):
        d = v.depth[i].astype(np.float32)
        row, col = np.unravel_index(np.argmin(d), d.shape)
        assert abs(col - v.pixels[i, 0]) <= 1.5 and abs(row - v.pixels[i, 1]) <= 1.5, (i, col, row, v.pixels[i])
        assert d.max() == 1.0  # the gel's footprint holds more than the sphere: empty pixels are far
    # Sensor pixel (column, row) and crop pixel grow the same way: left-right and top-bottom are kept.
    assert v.pixels[0, 0] < v.pixels[2, 0] < v.pixels[1, 0] and v.pixels[0, 1] < v.pixels[2, 1] < v.pixels[1, 1]


def test_deeper_presses_come_closer(sensor, sp, radius):
    assert list(np.argsort(sp.depths)) == [0, 1, 2, 3]
    nearest = press_rgbd(sensor, sp, radius).depth.reshape(4, -1).astype(np.float32).min(1)
    assert np.all(np.diff(nearest) < 0), nearest
    window = Framing().depth_window
    assert np.allclose(nearest, 0.5 - sp.depths / window, atol=2e-3)
    deeper = press_rgbd(sensor, sp, radius, depth_scale=1.5).depth.reshape(4, -1).astype(np.float32).min(1)
    assert np.all(deeper < nearest)
    # Measured from the first contact, as simulated touches are, the depth does not reach the input.
    contact = press_rgbd(sensor, sp, radius, reference="contact").depth.reshape(4, -1).astype(np.float32).min(1)
    assert np.allclose(contact, 0.5, atol=2e-3)


def test_sensor_sized_crops_align_with_the_tactile_image(sensor, sp, radius):
    framing = Framing(crop_extent="sensor")
    v = press_rgbd(sensor, sp, radius, framing=framing)
    # The sensor's view spans the crop: sensor pixel (c, r) lands at (c + 0.5) * 128 / width - 0.5.
    expect = (sp.centers + 0.5) * np.array([128 / sensor.width, 128 / sensor.height]) - 0.5
    assert np.allclose(crop_pixels(sensor, framing, sp.centers), expect)
    d = v.depth[0].astype(np.float32)
    row, col = np.unravel_index(np.argmin(d), d.shape)
    assert abs(col - expect[0, 0]) <= 1.5 and abs(row - expect[0, 1]) <= 1.5


def test_press_rgbd_refuses_bad_settings(sensor, sp, radius):
    with pytest.raises(TnfError, match="reference must be one of"):
        press_rgbd(sensor, sp, radius, reference="nope")
    with pytest.raises(TnfError, match="per view"):
        press_rgbd(sensor, sp, radius, framing=Framing(crop_distance="fixed"))
    with pytest.raises(TnfError, match="reaches the indenter's radius"):
        press_rgbd(sensor, sp, radius, depth_scale=10.0)


def test_generate_presses_with_a_trained_generator(checkpoint, sensor, sp, radius, taxim_presses):
    assert checkpoint_framing(checkpoint) == Framing()  # its synthetic dataset records no framing
    spread = dataclasses.replace(sp, centers=np.array([[12.0, 9.0], [66.0, 50.0], [40.0, 30.0], [20.0, 45.0]]))
    images = generate_presses(checkpoint, sensor, spread, radius)
    assert images.shape == (4, 60, 80, 3) and images.dtype == np.uint8
    # The generator sees each press where it is: images of presses at different places differ.
    assert all(np.abs(images[i].astype(int) - images[j]).max() >= 3 for i in range(4) for j in range(i))
    again = generate_presses(checkpoint, sensor, spread, radius)
    assert np.array_equal(images, again)  # the seed fixes the generator's dropout noise
    scores = report.score_rows([report.Row("T-N", images)], taxim_presses, spread, region_scale=1.5)["T-N"]
    assert set(scores) == set(report.ALL_METRICS)
    assert all(len(v) == 4 and np.all(np.isfinite(v)) for v in scores.values())
    assert all(-1 <= s <= 1 for s in scores["ssim_crop"])


def test_generate_presses_names_a_missing_checkpoint(tmp_path, sensor, sp, radius):
    with pytest.raises(TnfError, match="checkpoint not found"):
        generate_presses(tmp_path / "none.ckpt", sensor, sp, radius)
