"""Fitting a sensor's optics to real presses, the simulator's depth-controlled presses and calibrated shading,
calibration files, and the ``tnf calibrate`` stage end to end (with ``tnf touch`` using its result)."""

import json
import math
import shutil

import numpy as np
import pytest
from PIL import Image

from tnf.cli import main
from tnf.errors import TnfError
from tnf.real import realism
from tnf.real.calibrate import FitSettings, calibrate_sensor, centre_shifts, fit_calibration
from tnf.real.presses import at_sensor_size, contact_radius_from_depth, disk_masks, sphere_gaps
from tnf.registry import SENSORS, SIMULATORS
from tnf.sensors.calibration import FILE, Calibration, load_calibration

TINY = dict(falloffs=[0.05], depth_scales=[1.0], blurs=[2.0], table_size=9, refine_radius=0)
TRAIN = [0, 1, 2]
WARP = {"name": "warp_gel"}


@pytest.fixture(scope="module")
def sensor():
    return SENSORS.build("gelsight_mini")


@pytest.fixture(scope="module")
def fitted(taxim_presses, sensor):
    return fit_calibration(taxim_presses, sensor, WARP, TRAIN, FitSettings(**TINY))


# -- the fit ------------------------------------------------------------------------------------------


def test_fit_beats_the_background_on_training_presses(taxim_presses, sensor, fitted):
    cal, info = fitted
    assert cal.table.shape == (9, 9, 3) and cal.table.dtype == np.float32
    assert np.isfinite(cal.table).all()
    assert np.ptp(cal.table) > 1  # the presses changed the image: the table is not flat
    assert (cal.falloff, cal.blur_sigma, cal.noise_std, cal.max_slope) == (0.05, 2.0, 0.0, 1.5)
    assert info["train"] == TRAIN and len(info["search"]) == 1 and info["depth_scale"] == 1.0
    sp = at_sensor_size(taxim_presses, sensor, TRAIN)
    assert sp.frames.shape == (3, 240, 320, 3) and sp.background.shape == (240, 320, 3)
    assert np.array_equal(cal.background, sp.background)
    assert cal.size == (320, 240)
    # Background only: the error of predicting "no change" over the same contact regions.
    region = disk_masks(sp.background.shape[:2], sp.centers, 1.5 * sp.radii)
    assert region.shape == (3, 240, 320) and region.sum(axis=(1, 2)).min() > 100
    sq = (sp.frames.astype(np.float64) - sp.background.astype(np.float64)) ** 2
    background_mse = float(sq[region].mean())
    assert math.isfinite(info["train_region_mse"]) and info["train_region_mse"] > 0
    assert info["train_region_mse"] < 0.6 * background_mse
    # The simulator with the calibration renders what the fit promised (its own blur and rounding aside).
    rendered, _ = realism.render(sensor.calibrated(cal, "fitted"), WARP, sp, taxim_presses.radius_mm * 1e-3)
    render_mse = float(((rendered.astype(np.float64) - sp.frames) ** 2)[region].mean())
    assert render_mse == pytest.approx(info["train_region_mse"], rel=0.05)
    assert render_mse < 0.6 * background_mse


def test_at_sensor_size_scales_centres_and_radii(taxim_presses, sensor):
    sp = at_sensor_size(taxim_presses, sensor, [4, 0])
    assert sp.indices == [4, 0]
    for k, i in enumerate([4, 0]):
        col, row = taxim_presses.presses[i].center
        # 640x480 -> 320x240: pixel centres map as (c + 0.5) / 2 - 0.5.
        assert sp.centers[k].tolist() == pytest.approx([(col + 0.5) / 2 - 0.5, (row + 0.5) / 2 - 0.5])
        assert sp.radii[k] == pytest.approx(taxim_presses.contact_radius_px(i) / 2)
        assert sp.depths[k] == pytest.approx(taxim_presses.presses[i].depth_mm * 1e-3)


@pytest.mark.parametrize(
    "spec",
    [
        {"name": "gelsight_mini", "fov": 40.0},  # 0.0455 mm per pixel
        {"name": "gelsight_mini", "camera_distance": 0.02},
        {"name": "digit", "width": 320, "height": 240},
    ],
)
def test_sensor_of_another_pixel_size_is_refused(taxim_presses, spec):
    other = SENSORS.build(spec)
    with pytest.raises(TnfError, match=r"sees [0-9.]+ mm per pixel, the presses 0\.0590 mm at its size") as e:
        fit_calibration(taxim_presses, other, WARP, TRAIN, FitSettings(**TINY))
    assert "\n" not in str(e.value) and "sensor.fov" in str(e.value)


def test_sensor_of_another_aspect_ratio_is_refused(taxim_presses):
    with pytest.raises(TnfError, match=r"sensor 'digit' images are 240x320, the presses' 640x480: the aspect") as e:
        fit_calibration(taxim_presses, SENSORS.build("digit"), WARP, TRAIN, FitSettings(**TINY))
    assert "\n" not in str(e.value)


def test_half_size_sensor_matches_the_recording(taxim_presses):
    # At 160x120 the same field of view sees 0.118 mm per pixel: four of the recording's 0.0295 mm pixels.
    small = SENSORS.build({"name": "gelsight_mini", "width": 160, "height": 120})
    sp = at_sensor_size(taxim_presses, small, [0])
    assert sp.frames.shape == (1, 120, 160, 3)
    assert sp.radii[0] == pytest.approx(taxim_presses.contact_radius_px(0) / 4)


@pytest.mark.parametrize("bad", [[0, 24], [-1], [1, 100]])
def test_press_index_out_of_range(taxim_presses, sensor, bad):
    wrong = [i for i in bad if not 0 <= i < 24][0]
    with pytest.raises(TnfError, match=rf"press {wrong} does not exist: .* has presses 0-23") as e:
        fit_calibration(taxim_presses, sensor, WARP, bad, FitSettings(**TINY))
    assert "\n" not in str(e.value)


def test_calibrate_sensor_refuses_overlap_and_empty_splits(taxim_presses, sensor, tmp_path):
    with pytest.raises(TnfError, match="press 2 is in both train and test"):
        calibrate_sensor(taxim_presses, sensor, WARP, [0, 1, 2], [2, 16], FitSettings(**TINY), tmp_path / "o")
    with pytest.raises(TnfError, match="train and test each need at least one press"):
        calibrate_sensor(taxim_presses, sensor, WARP, [0], [], FitSettings(**TINY), tmp_path / "o")
    assert not (tmp_path / "o").exists()


# -- the simulator: presses to a depth, calibrated shading -------------------------------------------


def test_press_heights_to_a_penetration(sensor):
    sim = SIMULATORS.build(WARP, sensor=sensor, device="cpu")
    depths = np.array([0.1e-3, 0.3e-3, 0.6e-3], np.float32)
    gaps = sphere_gaps(sensor, np.array([[160.0, 120.0], [100.0, 80.0], [200.0, 150.0]]), 2e-3)
    assert gaps.shape == (3, 240, 320) and np.isinf(gaps).any()
    out = sim.press_heights(gaps, penetration=depths)
    assert out.hit.all()
    np.testing.assert_allclose(out.penetration, depths, rtol=1e-6)
    np.testing.assert_allclose(out.indentation.reshape(3, -1).max(1), depths, rtol=0.02)
    assert (out.force > 0).all() and out.force[0] < out.force[1] < out.force[2]
    # The deepest point faces the sphere's lowest point.
    r, c = np.unravel_index(out.indentation[2].argmax(), (240, 320))
    assert abs(r - 150) <= 1 and abs(c - 200) <= 1
    dx, dy = sensor.pixel_size()
    for b in range(3):
        d = float(depths[b])
        g = gaps[b] - gaps[b][np.isfinite(gaps[b])].min()  # gap to the sphere at first contact
        reach = np.where(np.isfinite(g), d - g, -1.0)  # how far the sphere reaches past the undeformed gel
        # Wherever the sphere crosses the undeformed gel (the geometric circle a = sqrt(R^2 - (R - d)^2)), the gel
        # takes its shape; outside, it falls off and never rises above the sphere's surface.
        inside = reach > 0
        a_px = contact_radius_from_depth(2.0, d * 1e3) * 1e-3 / dx
        assert inside.sum() == pytest.approx(math.pi * a_px**2, rel=0.1)
        assert (out.indentation[b][inside] >= reach[inside] - 1e-7).all()
        assert (out.indentation[b] >= -1e-9).all()
        # The contact mask is the area with gap <= d / 2 (the method of dimensionality reduction: Hertz's
        # a = sqrt(R d)), where the indentation follows the sphere (the coarse fall-off grid lets the gel sag a
        # few per cent of d below it at the contact's rim).
        hertz = np.isfinite(g) & (g <= d / 2)
        assert np.array_equal(out.contact[b], hertz)
        assert out.contact[b].sum() == pytest.approx(math.pi * 2e-3 * d / (dx * dy), rel=0.15)
        assert (out.indentation[b][hertz] <= reach[hertz] + 0.1 * d).all()
    # Same press by force: the force reported for a depth gives back that depth.
    again = sim.press_heights(gaps[1:2], force=float(out.force[1]))
    assert again.penetration[0] == pytest.approx(depths[1], rel=0.02)


def test_press_heights_needs_force_or_penetration(sensor):
    sim = SIMULATORS.build(WARP, sensor=sensor, device="cpu")
    gaps = sphere_gaps(sensor, np.array([[160.0, 120.0]]), 2e-3)
    for kwargs in ({}, {"force": 1.0, "penetration": 1e-4}):
        with pytest.raises(TnfError, match="give either force or penetration"):
            sim.press_heights(gaps, **kwargs)
    with pytest.raises(TnfError, match="penetration must be finite and >= 0"):
        sim.press_heights(gaps, penetration=-1e-4)


def _hand_calibration(sensor, table, slope_power=1.0):
    return Calibration(
        table=table.astype(np.float32),
        max_slope=1.0,
        blur_sigma=0.0,
        noise_std=0.0,
        falloff=0.1,
        background=np.full((sensor.height, sensor.width, 3), 128, np.uint8),
        slope_power=slope_power,
    )


def _tables(n=9):
    s = np.linspace(-1.0, 1.0, n)
    sx, sy = np.meshgrid(s, s)  # table[i(sy), j(sx)]
    linear = np.stack([60 * sx, 60 * sy, 30 * sx - 45 * sy + 5], -1)
    bumpy = np.random.default_rng(3).uniform(-80, 80, size=(n, n, 3))  # any bilinear mix-up shows here
    return {"linear": linear, "bumpy": bumpy}


@pytest.mark.parametrize("kind, power", [("linear", 1.0), ("bumpy", 1.0), ("bumpy", 0.5)])
def test_calibrated_kernel_matches_host_shading(sensor, kind, power):
    cal = _hand_calibration(sensor, _tables()[kind], power)
    cs = sensor.calibrated(cal, "hand-made")
    assert cs.calibration is cal
    sim = SIMULATORS.build(WARP, sensor=cs, device="cpu")
    assert sim.falloff == 0.1 and sim.noise_std == 0.0
    centers = np.array([[150.0, 110.0], [40.0, 200.0]])  # one near the border: the one-sided slopes there
    out = sim.press_heights(sphere_gaps(cs, centers, 2e-3), penetration=np.array([0.5e-3, 0.8e-3]))
    h0 = cs.gel_surface()
    expected = cal.background.astype(np.float64) + cal.shade(cs.surface_slopes(h0[None] - out.indentation))
    expected -= cal.shade(cs.surface_slopes(h0))
    expected = np.clip(np.floor(expected + 0.5), 0, 255)
    diff = np.abs(out.images.astype(np.float64) - expected)
    assert diff.max() <= 1
    assert (diff > 0).mean() < 0.01  # off by one only where float rounding lands on .5
    changed = (expected != 128).any(-1)
    assert changed.sum(axis=(1, 2)).min() > 500  # the presses did change the image
    if kind == "linear":
        # A table linear in the slope: red follows dh/dx, so it brightens on the contact's right flank (the
        # surface falls toward the centre from the right: outward height grows with x there) and darkens on the left.
        r0, c0 = 110, 150
        img = out.images[0].astype(int)
        assert img[r0, c0 + 15, 0] > 128 + 5 and img[r0, c0 - 15, 0] < 128 - 5
        assert abs(img[r0, c0 + 15, 1] - 128) <= 1  # green follows dh/dy, zero on the row through the centre


def test_uncalibrated_sensor_does_not_use_a_table(sensor):
    sim = SIMULATORS.build(WARP, sensor=sensor, device="cpu")
    assert sim.calibration is None and sim.falloff == 0.5


def test_calibration_of_another_size_is_refused(sensor):
    cal = _hand_calibration(SENSORS.build({"name": "gelsight_mini", "width": 160, "height": 120}), _tables()["linear"])
    with pytest.raises(TnfError, match=r"was made for 160x120 images, the sensor's are 320x240") as e:
        sensor.calibrated(cal, "small")
    assert "\n" not in str(e.value)


# -- calibration files ----------------------------------------------------------------------------------


def test_calibration_save_and_load_round_trip(sensor, tmp_path):
    cal = _hand_calibration(sensor, _tables()["bumpy"])
    cal.save(tmp_path / "cal")
    back = load_calibration(tmp_path / "cal")
    assert np.array_equal(back.table, cal.table) and np.array_equal(back.background, cal.background)
    assert (back.max_slope, back.blur_sigma, back.noise_std, back.falloff) == (1.0, 0.0, 0.0, 0.1)
    assert back.digest() == cal.digest()
    assert np.array_equal(np.asarray(Image.open(tmp_path / "cal" / "background.png")), cal.background)
    assert load_calibration(tmp_path / "cal" / FILE).digest() == cal.digest()  # the npz itself also works
    other = _hand_calibration(sensor, _tables()["linear"])
    assert other.digest() != cal.digest()
    # Through the sensor's config.
    s = SENSORS.build({"name": "gelsight_mini", "calibration": str(tmp_path / "cal")})
    assert s.calibration.digest() == cal.digest() and np.array_equal(s.background(), cal.background)


def _write_npz(path, **override):
    arrays = dict(
        table=np.zeros((9, 9, 3), np.float32),
        max_slope=1.0,
        blur_sigma=1.0,
        noise_std=0.0,
        falloff=0.1,
        background=np.zeros((240, 320, 3), np.uint8),
    )
    arrays.update(override)
    path.mkdir(parents=True, exist_ok=True)
    np.savez(path / FILE, **arrays)
    return path


@pytest.mark.parametrize(
    "override, pattern",
    [
        ({"table": np.zeros((9, 8, 3), np.float32)}, r"table must be a finite \[N, N, 3\] array, got \[9, 8, 3\]"),
        ({"table": np.zeros((9, 9, 2), np.float32)}, r"table must be a finite \[N, N, 3\] array, got \[9, 9, 2\]"),
        ({"table": np.zeros((81, 3), np.float32)}, r"table must be a finite \[N, N, 3\] array, got \[81, 3\]"),
        ({"table": np.full((9, 9, 3), np.nan, np.float32)}, r"table must be a finite"),
        ({"falloff": 0.0}, r"max_slope and falloff must be > 0"),
        ({"blur_sigma": -1.0}, r"blur_sigma and noise_std >= 0"),
    ],
)
def test_bad_calibration_file_is_one_line(tmp_path, override, pattern):
    folder = _write_npz(tmp_path / "cal", **override)
    with pytest.raises(TnfError, match=pattern) as e:
        load_calibration(folder)
    assert "\n" not in str(e.value)


def test_missing_or_unreadable_calibration_is_one_line(tmp_path):
    with pytest.raises(TnfError, match=r"sensor calibration not found: .*nowhere \(run `tnf calibrate` first") as e:
        load_calibration(tmp_path / "nowhere")
    assert "\n" not in str(e.value)
    folder = tmp_path / "partial"
    folder.mkdir()
    np.savez(folder / FILE, table=np.zeros((9, 9, 3), np.float32))  # no background etc.
    with pytest.raises(TnfError, match=r"is not readable") as e:
        load_calibration(folder)
    assert "\n" not in str(e.value)
    (folder / FILE).write_bytes(b"garbage")
    with pytest.raises(TnfError, match=r"is not readable") as e:
        load_calibration(folder)
    assert "\n" not in str(e.value)
    s = SENSORS.build({"name": "gelsight_mini", "calibration": str(tmp_path / "nowhere")})
    with pytest.raises(TnfError, match="sensor calibration not found"):
        s.background()


# -- the stage ------------------------------------------------------------------------------------------

STAGE = [
    "calibrate",
    "sensor=gelsight_mini",
    "progress=false",
    "calibrate.train=[0,1,2]",
    "calibrate.test=[16,17]",
    "calibrate.fit.table_size=9",
    "calibrate.fit.falloffs=[0.05]",
    "calibrate.fit.depth_scales=[1.0]",
    "calibrate.fit.blurs=[2.0]",
]


def test_calibrate_stage_then_touch_with_it(data_root, capsys):
    assert main(STAGE) == 0
    out = data_root / "calibration" / "gelsight_mini" / "default"
    for name in ("manifest.json", "calibration.npz", "background.png", "realism.json", "realism.md", "realism.png"):
        assert (out / name).is_file(), name
    assert (data_root / "presses" / "taxim_gelsight_mini" / "presses.json").is_file()
    record = json.loads((out / "realism.json").read_text())
    small, native = "tnf calibrated, 320x240", "tnf calibrated, 640x480"
    rows = ["no contact (f0)", "tnf uncalibrated", small, native]
    assert list(record["mean"]) == rows
    for label in rows:
        m = record["mean"][label]
        assert set(m) == set(realism.METRICS) | set(realism.CROP_METRICS)
        assert all(math.isfinite(v) for v in m.values())
        assert -1 <= m["ssim_region"] <= 1 and m["mse_region"] >= 0 and m["sharpness"] > 0
        assert len(record["per_press"][label]["ssim_region"]) == len(record["per_press"][label]["ssim_crop"]) == 2
    assert record["test"] == [16, 17] and record["fit"]["train"] == [0, 1, 2]
    mean = record["mean"]
    # The calibration is closer to the real held-out presses than the hand-set lights and the bare background.
    for other in ("no contact (f0)", "tnf uncalibrated"):
        assert mean[small]["mse_region"] < mean[other]["mse_region"]
        assert mean[native]["mse_crop"] < mean[other]["mse_crop"]
    # Rendered at the recording's size over its own background, the contact is sharper than upsampled.
    assert mean[native]["sharpness"] > mean[small]["sharpness"]
    text = (out / "realism.md").read_text()
    assert all(f"| {label} |" in text for label in rows) and "sharpness" in text
    cal = load_calibration(out)
    assert cal.table.shape == (9, 9, 3) and cal.size == (320, 240)
    assert Image.open(out / "realism.png").size[0] > 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["stage"] == "calibration" and manifest["item"] == ["gelsight_mini", "default"]

    # A second identical run is skipped and leaves the files alone.
    mtime = (out / "calibration.npz").stat().st_mtime_ns
    capsys.readouterr()
    assert main(STAGE) == 0
    assert "done, skipped" in capsys.readouterr().out
    assert (out / "calibration.npz").stat().st_mtime_ns == mtime

    # The same data root copied elsewhere: the calibration is still done there (no path in its key).
    moved = data_root.parent / "moved-root"
    shutil.copytree(data_root, moved)
    assert main([*STAGE, f"data_root={moved}"]) == 0
    assert "done, skipped" in capsys.readouterr().out
    shutil.rmtree(moved)

    # Overlapping train and test: one line, exit code 1.
    assert main([*STAGE[:-5], "calibrate.name=overlap", "calibrate.test=[2,16]", *STAGE[-4:]]) == 1
    err = capsys.readouterr().err
    assert "press 2 is in both train and test" in err and "Traceback" not in err
    assert len([line for line in err.splitlines() if line.strip()]) == 1
    assert not (data_root / "calibration" / "gelsight_mini" / "overlap" / "calibration.npz").exists()

    # tnf touch with the calibrated sensor: its touches sit on the calibration's background.
    touch = [
        "touch", "debug=tiny", "object_names=[ball]", "sensor=gelsight_mini", f"sensor.calibration={out}",
        "sensor.width=320", "sensor.height=240", "progress=false", "device=cpu",
    ]  # fmt: skip
    assert main(touch) == 0
    item = data_root / "touch" / "gelsight_mini" / "builtin" / "ball"
    bg = np.asarray(Image.open(item / "background.png"))
    assert bg.shape == (240, 320, 3)
    assert np.array_equal(bg, cal.background)
    m = json.loads((item / "manifest.json").read_text())
    assert m["config"]["sensor"]["calibration_digest"] == cal.digest()
    first = np.asarray(Image.open(item / m["touches"][0]["image"]))
    assert first.shape == (240, 320, 3)

    # The data root copied elsewhere, the sensor pointed at the copy's calibration: the touches are still done.
    moved = data_root.parent / "moved-root"
    shutil.copytree(data_root, moved)
    capsys.readouterr()
    copied = moved / "calibration" / "gelsight_mini" / "default"
    assert main([*touch[:4], f"sensor.calibration={copied}", *touch[5:], f"data_root={moved}"]) == 0
    assert "done, skipped" in capsys.readouterr().out


# -- sharper optics: node spacing, refined centres, the search's edges ----------------------------------


def test_slope_power_puts_nodes_at_small_slopes():
    from tnf.sensors.calibration import table_cells

    s = np.array([[0.0, 0.0], [0.04, -0.04], [1.0, 1.0], [3.0, -3.0]])
    i0, j0, fy, fx = table_cells(s, 11, 1.0, 1.0)
    assert j0.tolist() == [5, 5, 9, 9] and np.allclose(fx, [0, 0.2, 1, 1])
    i0, j0, fy, fx = table_cells(s, 11, 1.0, 0.5)
    # sqrt(0.04) = 0.2 of the half-width: one node past the centre, where a regular grid reaches 0.2 of a cell.
    assert j0.tolist() == [5, 6, 9, 9] and np.allclose(fx, [0, 0.0, 1, 1], atol=1e-9)
    assert i0.tolist() == [5, 4, 9, 0] and np.allclose(fy, [0, 0.0, 1, 0], atol=1e-9)


def test_slope_power_round_trips_and_changes_the_digest(sensor, tmp_path):
    cal = _hand_calibration(sensor, _tables()["bumpy"], slope_power=0.5)
    cal.save(tmp_path / "cal")
    back = load_calibration(tmp_path / "cal")
    assert back.slope_power == 0.5 and back.digest() == cal.digest()
    assert back.digest() != _hand_calibration(sensor, _tables()["bumpy"]).digest()


def _annotation_moved(presses, press, columns, folder):
    """``presses`` read again from ``folder`` with press ``press``'s annotated centre moved ``columns`` recording
    pixels to the right (the frames stay where they are)."""
    from tnf.real.presses import load_presses

    meta = json.loads((presses.folder / "presses.json").read_text())
    for p in meta["presses"]:
        p["image"] = str(presses.folder / p["image"])
    meta["presses"][press]["center_px"][0] += columns
    meta["background"] = str(presses.folder / meta["background"])
    (folder / "presses.json").write_text(json.dumps(meta))
    return load_presses(folder)


def test_refined_centres_undo_a_shift_of_the_annotations(taxim_presses, sensor, tmp_path):
    """Press 0's annotation moved 6 px (sensor size) to the right: the refinement moves it back, against the
    others (the first fit's pattern, which the presses are matched to, takes up a third of the move)."""
    moved = _annotation_moved(taxim_presses, 0, 6 * taxim_presses.width / sensor.width, tmp_path)
    st = FitSettings(**{**TINY, "refine_radius": 10})
    _, as_given = fit_calibration(taxim_presses, sensor, WARP, TRAIN, st)
    _, shifted = fit_calibration(moved, sensor, WARP, TRAIN, st)
    a, b = np.array(as_given["center_shifts_px"]), np.array(shifted["center_shifts_px"])
    assert a.shape == b.shape == (3, 2) and np.abs(a).max() <= 10
    moved_by = b - a
    assert moved_by[0, 0] - moved_by[1:, 0].mean() == pytest.approx(-6, abs=1.5)
    assert np.abs(moved_by[:, 1]).max() <= 1
    assert len(shifted["search"]) == 2  # the search ran again on the refined centres


def test_centre_shifts_find_a_moved_annotation_of_another_press(taxim_presses, sensor, fitted, tmp_path):
    """A press outside the fit, its annotation moved 6 px (sensor size) to the right: the fitted pattern's best
    match moves it back by those 6 px, in the recording's pixels, and leaves its rows alone."""
    k = taxim_presses.width / sensor.width
    cal, info = fitted
    st = FitSettings(**{**TINY, "refine_radius": 10})
    as_given = centre_shifts(taxim_presses, sensor, WARP, cal, info, [3, 4], st)
    moved = centre_shifts(_annotation_moved(taxim_presses, 3, 6 * k, tmp_path), sensor, WARP, cal, info, [3, 4], st)
    assert as_given.shape == (2, 2) and np.abs(as_given).max() <= 10 * k
    assert moved[0, 0] - as_given[0, 0] == pytest.approx(-6 * k, abs=k)
    assert moved[0, 1] == as_given[0, 1] and np.array_equal(moved[1], as_given[1])


def test_search_edges_name_the_list_to_extend():
    from tnf.real.calibrate import search_edges, search_steps

    st = FitSettings(**{**TINY, "falloffs": [0.02, 0.05, 0.1], "blurs": [0.0, 1.0, 2.0]})
    assert search_edges(st, 0.05, 1.0, 1.0) == []  # a single depth factor is no search
    assert search_edges(st, 0.05, 1.0, 0.0) == []  # a blur cannot go below 0
    lines = search_edges(st, 0.02, 1.0, 2.0)
    assert len(lines) == 2
    assert "calibrate.fit.falloffs: the fit chose 0.02, the smallest candidate" in lines[0]
    assert "calibrate.fit.blurs: the fit chose 2, the largest candidate" in lines[1]
    assert search_steps(st) == 3 + 1 + 3 - 2
    assert search_steps(FitSettings(**{**TINY, "refine_radius": 4})) == 2


def test_depth_factors_too_deep_for_the_sensor_are_left_out_of_the_search(taxim_presses):
    from tnf.real.calibrate import feasible_depth_scales, search_edges

    radius = taxim_presses.radius_mm * 1e-3
    sp = at_sensor_size(taxim_presses, SENSORS.build("gelsight_mini"), TRAIN)
    deepest = float(sp.depths.max())
    # A gel that stops 1.6 x the deepest press past first contact: x2 would press through it.
    shallow = SENSORS.build({"name": "gelsight_mini", "max_penetration": 1.6 * deepest})
    kept, skipped = feasible_depth_scales([1.0, 1.5, 2.0], sp, shallow, radius)
    assert kept == [1.0, 1.5]
    assert len(skipped) == 1 and skipped[0].startswith("calibrate.fit.depth_scales: x2 left out: press ")
    assert skipped[0].endswith(f"past the sensor's max_penetration {1.6e3 * deepest:g} mm")
    with pytest.raises(TnfError, match=r"^calibrate.fit.depth_scales: every factor of \[2.0\] presses too deep: x2"):
        feasible_depth_scales([2.0], sp, shallow, radius)
    # The indenter's radius bounds the factor too: no press goes past the ball's equator.
    deep_gel = SENSORS.build({"name": "gelsight_mini", "max_penetration": 10 * radius})
    factor = 1.1 * radius / deepest  # deeper than the ball's radius, within that gel
    kept, too_deep = feasible_depth_scales([1.0, factor], sp, deep_gel, radius)
    assert kept == [1.0] and too_deep[0].endswith("past the indenter's radius 2 mm")

    # The fit runs on the factors left, says which it left out, and calls the largest one left no edge.
    cal, info = fit_calibration(
        taxim_presses, shallow, WARP, TRAIN, FitSettings(**{**TINY, "depth_scales": [1.0, 1.5, 2.0]})
    )
    assert info["depth_scale"] in (1.0, 1.5) and {t["depth_scale"] for t in info["search"]} == {1.0, 1.5}
    assert info["edges"][0] == skipped[0]
    st = FitSettings(**{**TINY, "depth_scales": [1.0, 1.5, 2.0]})
    assert search_edges(st, 0.05, 1.5, 2.0, [1.0, 1.5]) == []
    assert "depth_scales: the fit chose 2, the largest" in search_edges(st, 0.05, 2.0, 2.0)[0]


def test_resized_calibration_keeps_the_optics_in_gel_units(sensor):
    cal = _hand_calibration(sensor, _tables()["bumpy"])
    cal.blur_sigma = 1.5
    big = cal.resized(np.zeros((480, 640, 3), np.uint8))
    assert big.size == (640, 480) and big.blur_sigma == 3.0
    assert np.array_equal(big.table, cal.table) and (big.falloff, big.max_slope) == (cal.falloff, cal.max_slope)
    assert cal.size == (320, 240)  # the original is left alone
    with pytest.raises(TnfError, match="aspect ratios differ"):
        cal.resized(np.zeros((480, 480, 3), np.uint8))


def test_fit_equals_the_least_squares_fit_of_the_blurred_design(taxim_presses, sensor):
    """The sparse design with the blur as matrices gives the normal equations and errors of the dense design
    blurred image by image (``scipy.ndimage.gaussian_filter1d``, edges repeated)."""
    from scipy.ndimage import gaussian_filter1d

    from tnf.real.calibrate import _Design, press_surfaces

    st = FitSettings(**TINY)
    sp = at_sensor_size(taxim_presses, sensor, TRAIN)
    design = _Design(sensor, sp, press_surfaces(sensor, WARP, sp, taxim_presses.radius_mm * 1e-3), st)
    n, k, blur = st.table_size, st.table_size**2, 1.5
    reg = st.smoothness * np.eye(k)
    ata, atb, parts = np.zeros((k, k)), np.zeros((k, 3)), []
    for b, (w, target, region) in enumerate(design.crops):
        r0, r1, c0, c1 = design.bounds[b]
        dense = w.toarray().reshape(r1 - r0, c1 - c0, k)
        dense = gaussian_filter1d(gaussian_filter1d(dense, blur, axis=0, mode="nearest"), blur, axis=1, mode="nearest")
        dense = dense.reshape(-1, k).astype(np.float64)
        ata += dense.T @ dense
        atb += dense.T @ target
        parts.append((dense[region], target[region]))
    x = np.linalg.solve(ata + reg, atb)
    err = sum(float(((d @ x - t) ** 2).sum()) for d, t in parts) / sum(t.size for _, t in parts)
    table, got = design.fit(blur, st, reg)
    assert table.shape == (n, n, 3)
    np.testing.assert_allclose(table.reshape(-1, 3), x, rtol=1e-3, atol=1e-3 * np.abs(x).max())
    assert got == pytest.approx(err, rel=1e-4)
    # Unblurred, the fit is the plain least squares of the sparse design.
    w_all = np.concatenate([w.toarray() for w, _, _ in design.crops]).astype(np.float64)
    t_all = np.concatenate([t for _, t, _ in design.crops])
    x0 = np.linalg.solve(w_all.T @ w_all + reg, w_all.T @ t_all)
    np.testing.assert_allclose(design.fit(0.0, st, reg)[0].reshape(-1, 3), x0, rtol=1e-3, atol=1e-3 * np.abs(x0).max())
