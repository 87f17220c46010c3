"""GelSight-specific behaviour: the plugin's registration, its YAML, its geometry and its moving markers."""

import numpy as np
import pytest

from tnf.registry import SENSORS, SIMULATORS, config_to_dict
from tnf.testing import compose


@pytest.fixture(scope="module")
def sensor():
    return SENSORS.build("gelsight")


def test_registered_from_the_plugin_distribution():
    entry = SENSORS.entry("gelsight")
    assert entry.origin == "tnf-gelsight"
    assert entry.obj.__module__ == "tnf_gelsight.sensor"


def test_the_defaults_are_the_yaml(sensor):
    cfg = compose("touch", ["sensor=gelsight"])
    assert config_to_dict(SENSORS.build(cfg.sensor).cfg) == config_to_dict(sensor.cfg)


def test_gelsight_mini_figures(sensor):
    assert (sensor.width, sensor.height) == (320, 240)
    assert sensor.gel_surface().max() == 0.0  # flat gel
    x, y = sensor.gel_grid()
    # The landscape image spans the whole 18.6 x 14.3 mm gel with a thin dark housing around it.
    assert 0.0186 < x.max() - x.min() < 0.021 and 0.0143 < y.max() - y.min() < 0.016
    mask = sensor.gel_mask()
    assert mask[120, 160] and not mask[120, 0] and not mask[120, -1]
    assert len(sensor.cfg.lights) == 4
    assert sensor.marker_rest_positions().shape == (63, 2)  # 9 x 7 markers at 2 mm


def test_lights_unlike_digit(sensor):
    bg = sensor.procedural_background(0).astype(float)  # no markers: compare the lighting alone
    # Red glows on the right, blue on the left, green at the bottom (Digit: red top right, green top left).
    assert bg[60:180, 250:300, 0].mean() > bg[60:180, 20:70, 0].mean() + 15
    assert bg[60:180, 20:70, 2].mean() > bg[60:180, 250:300, 2].mean() + 15
    assert bg[190:230, 100:220, 1].mean() > bg[10:50, 100:220, 1].mean() + 15
    digit = SENSORS.build("digit").background(0)[:240, :240].astype(float)
    assert np.abs(bg[:, 40:280].mean((0, 1)) - digit.mean((0, 1))).max() > 10


def _dark_blobs(img, sensor):
    """Marker centres ``[N, 2]`` (col, row) found in ``img``: dark connected blobs inside the gel."""
    from scipy import ndimage

    gray = img.astype(float).mean(-1)
    local = ndimage.uniform_filter(gray, 15)
    dark = (gray < 0.6 * local) & sensor.gel_mask()
    labels, n = ndimage.label(dark)
    sizes = ndimage.sum(dark, labels, range(1, n + 1))
    keep = [i + 1 for i, s in enumerate(sizes) if s >= 10]
    centres = ndimage.center_of_mass(dark, labels, keep)
    return np.array([(c, r) for r, c in centres])


def test_markers_visible_on_the_background(sensor):
    bg = sensor.background()
    found = _dark_blobs(bg, sensor)
    expected = sensor.marker_pixels()[0]
    assert len(found) == len(expected) == 63
    # Every printed marker is found where it should be, to a fraction of a pixel.
    dist = np.linalg.norm(found[:, None] - expected[None], axis=-1).min(0)
    assert dist.max() < 0.5
    # And dark: a marker's centre pixel keeps about (1 - darkness) of the light.
    c, r = np.rint(expected[31]).astype(int)
    plain = sensor.procedural_background(0)
    assert bg[r, c].mean() == pytest.approx((1 - sensor.cfg.marker_darkness) * plain[r, c].mean(), abs=2)
    assert np.array_equal(SENSORS.build({"name": "gelsight", "markers": False}).background(), plain)


def test_markers_move_away_from_a_press(sensor):
    x, y = sensor.gel_grid()
    # A sphere of radius 10 mm pressed 1 mm deep at (2 mm, 0): the gel takes the sphere's shape.
    r2 = (x - 0.002) ** 2 + y**2
    ind = np.clip(0.001 - r2 / (2 * 0.01), 0, None)[None].astype(np.float32)
    rest = sensor.marker_pixels()[0]
    moved = sensor.marker_pixels(ind)[0]
    shift = moved - rest
    centre = sensor._to_pixels(np.array([0.002, 0.0]))
    outward = rest - centre
    dist = np.linalg.norm(outward, axis=-1)
    near = (dist > 5) & (dist < 80)
    radial = (shift * outward).sum(-1) / np.maximum(dist, 1e-9)
    assert (radial[near] > 0.3).all(), "markers around the press move outward"
    assert np.abs(shift[dist > 160]).max() < 0.2, "markers far from the press stay put"
    assert np.abs(shift).max() > 2  # pixels


def test_decorate_redraws_markers_where_the_gel_moved(sensor):
    bg = sensor.background()
    x, y = sensor.gel_grid()
    ind = np.clip(0.001 - (x**2 + y**2) / 0.02, 0, None)[None].astype(np.float32)
    img = sensor.decorate(bg[None].copy(), ind)[0]
    found = _dark_blobs(img, sensor)
    expected = sensor.marker_pixels(ind)[0]
    assert len(found) == 63
    assert np.linalg.norm(found[:, None] - expected[None], axis=-1).min(0).max() < 0.7
    # Unchanged with nothing pressing (up to rounding).
    same = sensor.decorate(bg[None].copy(), np.zeros_like(ind))[0]
    assert np.abs(same.astype(int) - bg).max() <= 1


def test_press_moves_the_markers_in_the_image(sensor):
    import trimesh

    sim = SIMULATORS.build("warp_gel", sensor=sensor, device="cpu")
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.01)
    pose = np.eye(4)
    pose[:3, 3] = (0.0, 0.0, 0.04)
    out = sim.press(sphere, pose[None], 3.0, seed=0)
    assert out.hit[0] and out.contact[0].sum() > 500
    rest = sensor.marker_pixels()[0]
    found = _dark_blobs(out.images[0], sensor)
    expected = sensor.marker_pixels(out.indentation)[0]
    assert len(found) == 63
    err = np.linalg.norm(found[:, None] - expected[None], axis=-1).min(0)
    assert err.max() < 1.0, "every marker shows where the gel carried it"
    assert np.linalg.norm(expected - rest, axis=-1).max() > 2, "the press moved markers by pixels"


# -- a real, marker-free frame ------------------------------------------------------------------------


def _real_frame(path):
    """A smooth 320x240 frame without markers, as a recording's no-contact frame; saved to ``path``."""
    from PIL import Image

    rows, cols = np.mgrid[:240, :320]
    frame = np.stack([120 + cols // 8, 140 + rows // 8, np.full_like(rows, 160)], -1).astype(np.uint8)
    Image.fromarray(frame).save(path)
    return frame


def test_no_markers_over_a_real_background_by_default(tmp_path):
    frame = _real_frame(tmp_path / "background.png")
    sensor = SENSORS.build({"name": "gelsight", "background_image": str(tmp_path / "background.png")})
    assert sensor.cfg.markers is None and not sensor.draws_markers and not sensor.decorates
    assert np.array_equal(sensor.background(), frame)
    sim = SIMULATORS.build("warp_gel", sensor=sensor, device="cpu")
    x, y = sensor.gel_grid()
    gaps = ((x**2 + y**2) / 0.02)[None].astype(np.float32)  # a sphere of 10 mm radius, in gap form
    out = sim.press_heights(gaps, penetration=0.0005)
    assert out.contact[0].any() and len(_dark_blobs(out.images[0], sensor)) == 0
    # Asked for, the markers are drawn over the frame all the same.
    forced = SENSORS.build({"name": "gelsight", "background_image": str(tmp_path / "background.png"), "markers": True})
    assert forced.draws_markers and len(_dark_blobs(forced.background(), forced)) == 63


def test_no_markers_over_a_calibration_by_default(tmp_path):
    from tnf.sensors.calibration import Calibration

    frame = _real_frame(tmp_path / "frame.png")
    table = np.zeros((9, 9, 3), np.float32)
    Calibration(table, 1.5, 1.0, 0.0, 0.1, frame).save(tmp_path / "cal")
    sensor = SENSORS.build({"name": "gelsight", "calibration": str(tmp_path / "cal")})
    assert not sensor.draws_markers
    assert np.array_equal(sensor.background(), frame)
    assert SENSORS.build("gelsight").draws_markers  # the procedural background keeps them


def test_field_of_view_error_mentions_the_markers(tmp_path):
    import json

    from tnf.errors import TnfError
    from tnf.real.presses import at_sensor_size, load_presses

    _real_frame(tmp_path / "background.png")
    _real_frame(tmp_path / "00000.png")
    meta = {
        "format": "tnf.presses/1",
        "mm_per_pixel": 0.05,  # the sensor sees about 0.062 mm per pixel
        "indenter": {"shape": "sphere", "radius_mm": 2.0},
        "presses": [{"image": "00000.png", "center_px": [160, 120], "contact_radius_px": 20}],
    }
    (tmp_path / "presses.json").write_text(json.dumps(meta))
    presses = load_presses(tmp_path)
    with pytest.raises(TnfError, match=r"set sensor\.fov or sensor\.camera_distance to match; .*markers") as e:
        at_sensor_size(presses, SENSORS.build("gelsight"), [0])
    assert "sensor.markers=false" in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(TnfError, match=r"sensor\.camera_distance to match$"):
        at_sensor_size(presses, SENSORS.build({"name": "gelsight", "markers": False}), [0])
