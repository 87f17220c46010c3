"""Press folders: the importer of Taxim's recording, the depth/contact-radius geometry and the checks of
``load_presses`` on hand-made folders."""

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tnf.errors import TnfError
from tnf.real.presses import (
    INDEX,
    TAXIM_BALL_RADIUS_MM,
    at_sensor_size,
    check_depths,
    contact_radius_from_depth,
    depth_from_contact_radius,
    import_taxim,
    load_presses,
    taxim_recording,
)

# -- the taxim importer -----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def taxim_npz():
    with np.load(taxim_recording("gelsight_mini") / "dataPack.npz", allow_pickle=True) as d:
        return {k: d[k] for k in ("f0", "imgs", "touch_center", "touch_radius")}


def test_import_taxim_writes_the_recording_as_rgb_presses(taxim_presses, taxim_npz):
    p = taxim_presses
    assert len(p) == 24
    assert (p.width, p.height) == (640, 480)
    assert p.mm_per_pixel == pytest.approx(0.0295)
    assert p.radius_mm == TAXIM_BALL_RADIUS_MM == 2.0
    # The npz holds OpenCV BGR frames; the folder RGB ones.
    first = p.frame(0)
    assert first.shape == (480, 640, 3) and first.dtype == np.uint8
    assert np.array_equal(first, taxim_npz["imgs"][0][..., ::-1])
    assert not np.array_equal(first, taxim_npz["imgs"][0])  # the channels did change order
    assert np.array_equal(p.frame(23), taxim_npz["imgs"][23][..., ::-1])
    assert np.array_equal(p.background(), taxim_npz["f0"][..., ::-1])
    centers, radii = taxim_npz["touch_center"], taxim_npz["touch_radius"]
    for i, press in enumerate(p.presses):
        assert press.image == p.folder / f"frames/{i:05d}.png"
        # touch_center is (x, y) = (column, row), as center_px.
        assert press.center == (float(centers[i][0]), float(centers[i][1]))
        assert press.contact_radius_mm == pytest.approx(float(radii[i]) * 0.0295, rel=1e-9)
        assert p.contact_radius_px(i) == pytest.approx(float(radii[i]), rel=1e-9)
        assert press.depth_mm == pytest.approx(depth_from_contact_radius(2.0, float(radii[i]) * 0.0295), rel=1e-9)
        assert 0 < press.depth_mm < 2.0
    # The centre is a column, row pair: the first press's contact is where its frame differs from the background.
    diff = np.abs(p.frame(0).astype(int) - p.background().astype(int)).sum(-1)
    rows, cols = np.nonzero(diff > 60)
    col, row = p.presses[0].center
    assert abs(np.median(cols) - col) < p.contact_radius_px(0) and abs(np.median(rows) - row) < p.contact_radius_px(0)


def test_import_taxim_folder_is_a_valid_press_folder(taxim_presses):
    meta = json.loads((taxim_presses.folder / INDEX).read_text())
    assert meta["format"] == "tnf.presses/1"
    again = load_presses(taxim_presses.folder)
    assert again.presses == taxim_presses.presses and again.mm_per_pixel == taxim_presses.mm_per_pixel


def test_import_taxim_unknown_recording_is_one_line(tmp_path):
    with pytest.raises(TnfError, match="taxim has no recording 'no_such_sensor'.*gelsight_mini") as e:
        import_taxim("no_such_sensor", tmp_path / "out")
    assert "\n" not in str(e.value)


# -- geometry -----------------------------------------------------------------------------------------


def test_depth_and_contact_radius_are_inverse():
    # A 5 mm sphere pressed 1 mm deep crosses the plane in a circle of sqrt(25 - 16) = 3 mm.
    assert contact_radius_from_depth(5.0, 1.0) == pytest.approx(3.0)
    assert depth_from_contact_radius(5.0, 3.0) == pytest.approx(1.0)
    assert contact_radius_from_depth(2.0, 0.0) == 0.0 and depth_from_contact_radius(2.0, 0.0) == 0.0
    assert contact_radius_from_depth(2.0, 2.0) == pytest.approx(2.0)  # pressed to its equator
    for depth in (0.001, 0.05, 0.3, 0.9, 1.5, 1.99):
        a = contact_radius_from_depth(2.0, depth)
        assert a == pytest.approx(math.sqrt(4.0 - (2.0 - depth) ** 2))
        assert depth_from_contact_radius(2.0, a) == pytest.approx(depth, rel=1e-9, abs=1e-12)
    for a in (0.1, 0.6, 1.15, 1.9):
        assert contact_radius_from_depth(2.0, depth_from_contact_radius(2.0, a)) == pytest.approx(a, rel=1e-9)


def test_geometry_refuses_a_depth_or_contact_past_the_radius():
    with pytest.raises(TnfError, match=r"depth 2\.5 mm is outside 0 to the indenter's radius 2 mm"):
        contact_radius_from_depth(2.0, 2.5)
    with pytest.raises(TnfError, match=r"depth -0\.1 mm is outside"):
        contact_radius_from_depth(2.0, -0.1)
    with pytest.raises(TnfError, match=r"contact radius 2\.5 mm is outside 0 to the indenter's radius 2 mm"):
        depth_from_contact_radius(2.0, 2.5)


# -- depths against the indenter -----------------------------------------------------------------------


def test_check_depths_passes_depths_below_the_radius():
    d = check_depths([0.3, 1.2, 1.99], 2.0, "p/presses.json")
    assert d.dtype == np.float64 and d.tolist() == [0.3, 1.2, 1.99]


@pytest.mark.parametrize(
    "bad, pattern",
    [
        (2.0, r"depth 2 mm is not smaller than the indenter's radius 2 mm"),
        (2.6, r"depth 2\.6 mm is not smaller than the indenter's radius 2 mm"),
        (float("nan"), r"depth nan mm must be a finite number > 0"),
        (float("inf"), r"depth inf mm must be a finite number > 0"),
        (0.0, r"depth 0 mm must be a finite number > 0"),
        (-0.2, r"depth -0\.2 mm must be a finite number > 0"),
    ],
)
def test_check_depths_names_the_file_and_the_press(bad, pattern):
    # A depth factor of 2 on presses 5, 6, 7: press 6 goes past the ball.
    where = "p/presses.json at depth x2"
    with pytest.raises(TnfError, match=rf"^p/presses\.json at depth x2: press 6: {pattern}$") as e:
        check_depths([0.4, bad, 0.8], 2.0, where, presses=[5, 6, 7])
    assert "\n" not in str(e.value)


def test_at_sensor_size_checks_the_depths(tmp_path):
    from tnf.registry import SENSORS

    p = load_presses(_folder(tmp_path / "p"))
    deep = dataclasses.replace(p.presses[1], depth_mm=2.4)
    p = dataclasses.replace(p, presses=(p.presses[0], deep, p.presses[2]))
    sensor = SENSORS.build({"name": "digit", "width": W, "height": H})
    with pytest.raises(TnfError, match=r"presses\.json: press 1: depth 2\.4 mm is not smaller than the indenter"):
        at_sensor_size(p, sensor, [0, 1])


# -- hand-made press folders ----------------------------------------------------------------------------

W, H = 64, 48


def _png(path: Path, array: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(array).save(path)


def _folder(root: Path) -> Path:
    """A valid 64x48 press folder of three presses (two by contact radius, one by depth)."""
    root.mkdir(parents=True, exist_ok=True)
    bg = np.zeros((H, W, 3), np.uint8)
    bg[..., 0], bg[..., 1], bg[..., 2] = 10, 120, 230  # distinct channels: RGB order is checked
    _png(root / "background.png", bg)
    for i in range(3):
        f = bg.copy()
        f[20:30, 30:40] = (200, 50 + i, 5)
        _png(root / f"frames/{i:05d}.png", f)
    meta = {
        "format": "tnf.presses/1",
        "mm_per_pixel": 0.05,
        "indenter": {"shape": "sphere", "radius_mm": 2.0},
        "background": "background.png",
        "presses": [
            {"image": "frames/00000.png", "center_px": [35, 25], "contact_radius_px": 10},
            {"image": "frames/00001.png", "center_px": [50.5, 40], "contact_radius_px": 4.5},
            {"image": "frames/00002.png", "center_px": [0, 0], "depth_mm": 0.4},
        ],
    }
    (root / INDEX).write_text(json.dumps(meta))
    return root


def _edit(root: Path, change) -> Path:
    meta = json.loads((root / INDEX).read_text())
    change(meta)
    (root / INDEX).write_text(json.dumps(meta))  # json writes NaN as NaN, which json.loads reads back
    return root


def _one_line_error(root: Path, pattern: str) -> str:
    with pytest.raises(TnfError, match=pattern) as e:
        load_presses(root)
    msg = str(e.value)
    assert "\n" not in msg
    return msg


def test_hand_made_folder_loads(tmp_path):
    p = load_presses(_folder(tmp_path / "p"))
    assert len(p) == 3 and (p.width, p.height) == (W, H)
    assert p.mm_per_pixel == 0.05 and p.radius_mm == 2.0
    assert p.presses[0].center == (35.0, 25.0) and p.presses[1].center == (50.5, 40.0)
    assert p.presses[0].contact_radius_mm == pytest.approx(0.5)
    assert p.presses[0].depth_mm == pytest.approx(2.0 - math.sqrt(4.0 - 0.25))
    assert p.contact_radius_px(1) == pytest.approx(4.5)
    assert p.presses[2].depth_mm == pytest.approx(0.4)
    assert p.presses[2].contact_radius_mm == pytest.approx(math.sqrt(4.0 - 1.6**2))
    assert p.background()[0, 0].tolist() == [10, 120, 230]
    f = p.frame(1)
    assert f.shape == (H, W, 3) and f[25, 35].tolist() == [200, 51, 5] and f[0, 0].tolist() == [10, 120, 230]


def test_grey_and_rgba_frames_read_as_rgb(tmp_path):
    root = _folder(tmp_path / "p")
    Image.fromarray(np.full((H, W), 77, np.uint8)).save(root / "frames/00000.png")  # mode L
    Image.fromarray(np.full((H, W, 4), 90, np.uint8)).save(root / "frames/00001.png")  # mode RGBA
    p = load_presses(root)
    assert p.frame(0).shape == (H, W, 3) and (p.frame(0) == 77).all()
    assert p.frame(1).shape == (H, W, 3) and (p.frame(1) == 90).all()


def test_frame_of_another_size(tmp_path):
    root = _folder(tmp_path / "p")
    _png(root / "frames/small.png", np.zeros((24, 32, 3), np.uint8))
    _edit(root, lambda m: m["presses"][1].update(image="frames/small.png"))
    msg = _one_line_error(root, r"press 1: frame frames/small.png is 32x24, the background 64x48")
    assert INDEX in msg


@pytest.mark.parametrize("center", [[64, 10], [10, 48], [-1, 10], [10, -0.5], [40, 50]])
def test_center_outside_the_frame(tmp_path, center):
    root = _edit(_folder(tmp_path / "p"), lambda m: m["presses"][2].update(center_px=center))
    _one_line_error(root, rf"press 2: center_px \[{center[0]:g}, {center[1]:g}\] is outside the 64x48 frame")


def test_center_is_column_then_row(tmp_path):
    # [50, 40] is inside a 64-wide, 48-high frame; [40, 50] (row 50) is not: see the parametrised case above.
    p = load_presses(_edit(_folder(tmp_path / "p"), lambda m: m["presses"][2].update(center_px=[63, 47])))
    assert p.presses[2].center == (63.0, 47.0)


@pytest.mark.parametrize("center", [[1, 2, 3], 5, "1,2"])
def test_center_not_a_pair(tmp_path, center):
    root = _edit(_folder(tmp_path / "p"), lambda m: m["presses"][0].update(center_px=center))
    _one_line_error(root, r"press 0: center_px must be \[column, row\]")


def test_contact_radius_larger_than_indenter(tmp_path):
    # 50 px x 0.05 mm = 2.5 mm against a 2 mm ball.
    root = _edit(_folder(tmp_path / "p"), lambda m: m["presses"][1].update(contact_radius_px=50))
    msg = _one_line_error(
        root, r"press 1: contact radius 2\.500 mm \(50 px\) is not smaller than the indenter's radius 2 mm"
    )
    assert "mm_per_pixel" in msg
    # Exactly the radius is refused too.
    _edit(root, lambda m: m["presses"][1].update(contact_radius_px=40))
    _one_line_error(root, r"press 1: contact radius 2\.000 mm")


def test_depth_larger_than_indenter(tmp_path):
    root = _edit(_folder(tmp_path / "p"), lambda m: m["presses"][2].update(depth_mm=2.5))
    _one_line_error(root, r"press 2: depth 2\.5 mm is not smaller than the indenter's radius 2 mm")


def test_missing_background(tmp_path):
    root = _folder(tmp_path / "p")
    (root / "background.png").unlink()
    _one_line_error(root, r"background frame background\.png is missing")


def test_missing_frame(tmp_path):
    root = _folder(tmp_path / "p")
    (root / "frames/00001.png").unlink()
    _one_line_error(root, r"press 1: frame frames/00001\.png not found")


def test_unreadable_frame(tmp_path):
    root = _folder(tmp_path / "p")
    (root / "frames/00001.png").write_bytes(b"not a png")
    _one_line_error(root, r"00001\.png is not a readable image")


def test_both_or_neither_radius_and_depth(tmp_path):
    root = _edit(_folder(tmp_path / "p"), lambda m: m["presses"][0].update(depth_mm=0.3))
    _one_line_error(root, r"press 0: give exactly one of contact_radius_px and depth_mm")
    _edit(root, lambda m: [m["presses"][0].pop(k) for k in ("depth_mm", "contact_radius_px")])
    _one_line_error(root, r"press 0: give exactly one of contact_radius_px and depth_mm")


@pytest.mark.parametrize("value", ["0.05", None, True, [0.05], 0, -0.05])
def test_bad_mm_per_pixel(tmp_path, value):
    root = _edit(_folder(tmp_path / "p"), lambda m: m.update(mm_per_pixel=value))
    _one_line_error(root, r"mm_per_pixel: (expected a finite number|must be > 0), got")


@pytest.mark.parametrize(
    "change, pattern",
    [
        (lambda m: m.update(mm_per_pixel=float("nan")), r"mm_per_pixel: expected a finite number, got nan"),
        (lambda m: m.update(mm_per_pixel=float("inf")), r"mm_per_pixel: expected a finite number, got inf"),
        (lambda m: m["indenter"].update(radius_mm=float("nan")), r"indenter\.radius_mm: expected a finite number"),
        (lambda m: m["presses"][2].update(depth_mm=float("nan")), r"press 2: depth_mm: expected a finite number"),
        (lambda m: m["presses"][0].update(contact_radius_px=float("nan")), r"press 0: contact_radius_px: expected"),
        (lambda m: m["presses"][1].update(center_px=[float("nan"), 3]), r"press 1: center_px: expected a finite"),
    ],
)
def test_nan_and_inf(tmp_path, change, pattern):
    _one_line_error(_edit(_folder(tmp_path / "p"), change), pattern)


@pytest.mark.parametrize(
    "change, pattern",
    [
        (lambda m: m.pop("indenter"), r"missing key 'indenter'"),
        (lambda m: m.pop("presses"), r"missing key 'presses'"),
        (lambda m: m.update(presses=[]), r"presses must be a non-empty list"),
        (lambda m: m["indenter"].update(shape="cube"), r"indenter\.shape must be one of sphere, got 'cube'"),
        (lambda m: m["indenter"].update(radius_mm=-1), r"indenter\.radius_mm: must be > 0"),
        (lambda m: m["presses"][1].pop("image"), r"press 1: needs image and center_px"),
        (lambda m: m["presses"][0].update(contact_radius_px=0), r"press 0: contact_radius_px: must be > 0"),
    ],
)
def test_other_bad_entries(tmp_path, change, pattern):
    _one_line_error(_edit(_folder(tmp_path / "p"), change), pattern)


def test_not_a_press_folder(tmp_path):
    _one_line_error(tmp_path, r"no presses\.json in .*: not a press folder")
    (tmp_path / INDEX).write_text("{not json")
    _one_line_error(tmp_path, r"presses\.json is not valid JSON")
    (tmp_path / INDEX).write_text("[1, 2]")
    _one_line_error(tmp_path, r"expected a JSON object, got list")


def test_sixteen_bit_frame_is_refused(tmp_path):
    """PIL reads a 16-bit grey PNG as mode I;16 (I in older Pillow), which clips to white when converted to RGB."""
    root = _folder(tmp_path / "p")
    Image.fromarray(np.full((H, W), 30000, np.uint16)).save(root / "frames/00001.png")
    _one_line_error(root, r"00001\.png has I(;16)? pixels: press frames must be 8-bit RGB")


def test_truncated_frame_is_refused_on_loading(tmp_path):
    root = _folder(tmp_path / "p")
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (H, W, 3), np.uint8)).save(root / "frames/00001.png")
    data = (root / "frames/00001.png").read_bytes()
    (root / "frames/00001.png").write_bytes(data[: len(data) // 2])
    _one_line_error(root, r"00001\.png is not a readable image: image file is truncated")


def test_other_format_is_refused(tmp_path):
    root = _edit(_folder(tmp_path / "p"), lambda m: m.update(format="tnf.presses/2"))
    _one_line_error(root, r"format 'tnf\.presses/2' is not 'tnf\.presses/1'")


def test_digest_follows_the_frames_not_only_the_index(tmp_path):
    """Frames written again under the same names (e.g. with their channels swapped) are other presses."""
    from tnf.real.presses import presses_digest

    root = _folder(tmp_path / "p")
    before = presses_digest(load_presses(root))
    frame = np.asarray(Image.open(root / "frames/00001.png"))
    _png(root / "frames/00001.png", np.ascontiguousarray(frame[..., ::-1]))
    assert presses_digest(load_presses(root)) != before
    _png(root / "background.png", np.zeros((H, W, 3), np.uint8))
    assert presses_digest(load_presses(root)) != before


def test_indices_name_their_setting(tmp_path):
    from tnf.real.presses import check_indices

    p = load_presses(_folder(tmp_path / "p"))
    check_indices(p, [0, 1, 2], "calibrate.train")
    with pytest.raises(TnfError, match=r"^calibrate\.test: press 3 does not exist: .* has presses 0-2$"):
        check_indices(p, [0, 3], "calibrate.test")


def test_calibrate_checks_the_split_before_fitting(tmp_path):
    """A test press past the folder's end stops before the fit, naming the setting, and writes nothing."""
    from tnf.real.calibrate import FitSettings, calibrate_sensor
    from tnf.sensors.gelsight_mini import GelSightMini

    p = load_presses(_folder(tmp_path / "p"))
    sensor = GelSightMini(GelSightMini.Config())
    with pytest.raises(TnfError, match=r"^calibrate\.test: press 5 does not exist"):
        calibrate_sensor(p, sensor, {"name": "warp_gel"}, [0, 1], [5], FitSettings(), tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_aspect_ratio_error_names_a_size(tmp_path):
    from tnf.sensors.gelsight_mini import GelSightMini

    p = load_presses(_folder(tmp_path / "p"))
    sensor = GelSightMini(dataclasses.replace(GelSightMini.Config(), width=60, height=80))
    with pytest.raises(TnfError, match=r"aspect ratios differ; .* e\.g\. sensor\.width=60 sensor\.height=45$"):
        at_sensor_size(p, sensor, [0])
