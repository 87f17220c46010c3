"""`tnf pair` end to end on hand-made capture, scene and touch items; resuming; clear errors."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from tests.data.pair_inputs import ASSETS, make_inputs, touch_colour
from tnf.data import SPLITS, PairDataset, open_pairs, resize_uint8
from tnf.errors import TnfError
from tnf.stages.pair import run
from tnf.testing import compose

BASE = ["debug=tiny", "progress=false", "device=cpu", "pair.novel_objects=[box]"]


def build(overrides=()):
    run(compose("pair", [*BASE, *overrides]))


def test_pair_end_to_end(data_root):
    make_inputs(data_root)
    build(["pair.keep_cache=true"])
    folder = data_root / "pairs" / "digit-hashgrid"
    a = open_pairs(folder)
    m = a.manifest
    assert m["objects"] == ["ball", "box"] and m["novel_objects"] == ["box"]
    assert m["counts"] == {"train": 3, "val": 1, "novel_view": 2, "novel_object": 6}
    assert m["sensor"]["name"] == "digit" and m["scene_source"] == "fitted"
    assert m["scene_checkpoints"]["ball"].endswith("scenes/hashgrid/builtin/ball/scene.pt")
    # Each crop is sized at its touch's first contact: no fixed crop; 0.06 m is the reference distance.
    pre = m["preprocess"]
    assert pre["crop_px"] == {} and pre["crop_distance"] == "contact" and pre["depth_norm"] == "contact"
    assert pre["footprint_distance"] == pytest.approx(0.06)
    assert len(a) == 12 and a.rgb.shape == (12, 128, 128, 3) and a.depth.dtype == np.float16
    assert [SPLITS[s] for s in a.split[:6]] == ["train", "train", "train", "val", "novel_view", "novel_view"]
    assert list(a.touch_index) == list(range(6)) * 2 and list(a.object_id) == [0] * 6 + [1] * 6
    # Tactile images are the touch PNGs scaled to 128 x 128; the background is the sensor's.
    for row in (0, 7):
        assert (a.tactile[row] == touch_colour(row // 6, row % 6)).all()
    bg = resize_uint8(np.asarray(Image.open(ASSETS / "bg_digit_240_320.jpg").convert("RGB")))
    assert a.backgrounds.shape == (1, 128, 128, 3) and (a.backgrounds[0] == bg).all()
    # RGB-D: the camera looks at the sphere's centre along the touch axis, so the centre pixel shows the
    # surface facing the camera (colour (n + 1) / 2, n = the direction to the start pose) at depth 0.5.
    touches = _touches(data_root, "ball")
    for row in range(6):
        n = np.asarray(touches[row]["start_c2w"])[:3, 2]
        np.testing.assert_allclose(a.rgb[row, 63:65, 63:65].reshape(-1, 3).mean(0), (n + 1) / 2 * 255, atol=4)
        d = a.depth[row].astype(np.float32)
        assert d[63:65, 63:65].min() == pytest.approx(0.5, abs=0.01)
        assert d.min() >= 0.49  # the centre is the nearest point
        # The gel's 30 mm x 1.5 at the first contact, 0.06 m: half-width 20.6 deg. The edge centres hit the
        # sphere (angular radius 23.6 deg), the corners miss.
        assert 0.5 < d[64, 1] < 1 and 0.5 < d[1, 64] < 1 and d[0, 0] == 1
    assert len(list((folder / "previews").glob("*.png"))) == 2
    ds = PairDataset(folder, splits=("novel_object",))
    assert len(ds) == 6 and int(ds[0]["object_id"]) == 1

    # Resuming: done -> nothing rewritten; other held-out objects -> reassembled from the kept caches.
    cache = data_root / "pairs" / ".cache" / "digit-hashgrid" / "builtin" / "ball" / "manifest.json"
    stamp, dstamp = cache.stat().st_mtime_ns, (folder / "manifest.json").stat().st_mtime_ns
    build(["pair.keep_cache=true"])
    assert (folder / "manifest.json").stat().st_mtime_ns == dstamp
    build(["pair.keep_cache=true", "pair.novel_objects=[ball]"])
    assert cache.stat().st_mtime_ns == stamp
    assert open_pairs(folder).manifest["counts"]["novel_object"] == 6
    assert open_pairs(folder).manifest["novel_objects"] == ["ball"]


def _touches(root, obj):
    import json

    return json.loads((root / "touch" / "digit" / "builtin" / obj / "manifest.json").read_text())["touches"]


def test_cache_removed_and_name_option(data_root):
    make_inputs(data_root, touches=2)
    build(["pair.name=mine", "pair.crop_px=32", "pair.depth_norm=minmax"])
    a = open_pairs(data_root / "pairs" / "mine")
    assert a.manifest["preprocess"]["crop_px"] == {"ball": 32, "box": 32}
    assert not (data_root / "pairs" / ".cache" / "mine").exists()
    assert a.depth.astype(np.float32).min() == 0.0  # minmax: the nearest point is 0


def test_missing_scene_names_object_and_stage(data_root):
    make_inputs(data_root, scenes=False)
    with pytest.raises(TnfError, match=r"'ball' has touches but no fitted hashgrid scene.*tnf fit-scene"):
        build()
    assert not (data_root / "pairs" / "digit-hashgrid").exists()


def test_missing_touches(data_root):
    make_inputs(data_root, objects=("ball",))
    with pytest.raises(TnfError, match=r"touch.*box.*tnf touch object=box"):
        build()


def test_sensor_mismatch(data_root):
    make_inputs(data_root)
    with pytest.raises(TnfError, match=r"sensor mismatch.*gel_width"):
        build(["sensor.gel_width=0.025"])


def test_touches_of_another_calibration(data_root):
    import json

    make_inputs(data_root)
    path = data_root / "touch" / "digit" / "builtin" / "ball" / "manifest.json"
    manifest = json.loads(path.read_text())
    manifest["sensor"]["calibration_digest"] = "0123456789abcdef"
    path.write_text(json.dumps(manifest))
    with pytest.raises(TnfError, match=r"'ball'.*made with calibration 0123456789abcdef, this config's digit has no"):
        build()


def test_a_calibration_is_its_content_not_its_folder(tmp_path):
    """Touches made with a calibration at one path pass the check for a sensor with a copy of it at another (a data
    root copied elsewhere); another calibration's content does not."""
    from types import SimpleNamespace

    from tests.sensors.calibrations import random_calibration
    from tnf.data.pairing import _check_sensor
    from tnf.registry import SENSORS
    from tnf.sensors.calibration import Calibration

    cal = random_calibration()
    for name in ("a", "b"):
        cal.save(tmp_path / name)
    other = Calibration(**{**cal.__dict__, "blur_sigma": 3.0})
    other.save(tmp_path / "c")

    def described(folder):
        return SENSORS.build(
            {"name": "gelsight_mini", "width": 320, "height": 240, "calibration": str(folder)}
        ).describe()

    a = described(tmp_path / "a")
    assert "calibration" not in a["config"] and a["calibration_digest"] == cal.digest()
    item = SimpleNamespace(manifest={"sensor": a}, folder=tmp_path)
    _check_sensor(item, described(tmp_path / "b"), "ball")
    with pytest.raises(TnfError, match=f"made with calibration {cal.digest()}, this config's gelsight_mini has"):
        _check_sensor(item, described(tmp_path / "c"), "ball")


def test_crop_larger_than_image(data_root):
    make_inputs(data_root)
    with pytest.raises(TnfError, match="larger than the 64x64 image"):
        build(["pair.crop_px=100"])


@pytest.mark.parametrize(
    "override,expected",
    [
        ("pair.crop_distance=median", "crop_distance must be one of contact, fixed, got 'median'"),
        ("pair.depth_norm=mean", "depth_norm must be one of contact, center, minmax, got 'mean'"),
        ("pair.depth_window=0", "depth_window must be > 0 metres"),
        ("pair.crop_margin=-1", "crop_margin must be > 0"),
        ("pair.render_px=0", "render_px must be at least 1 pixel"),
        ("pair.crop_extent=gel", "crop_extent must be one of footprint, sensor, got 'gel'"),
        ("pair.crop_extent=sensor pair.crop_px=32", "crop_extent=sensor frames each view at its contact"),
        ("pair.prior=true", "pair.prior needs crops pixel-aligned with the tactile image"),
    ],
)
def test_bad_framing_is_refused_before_anything_is_written(data_root, override, expected):
    make_inputs(data_root)
    with pytest.raises(TnfError, match=expected):
        build(override.split())
    assert not (data_root / "pairs").exists()


def test_sensor_extent_is_stored_for_generation(data_root):
    from tnf.registry import SENSORS

    make_inputs(data_root)
    build(["pair.crop_extent=sensor"])
    pre = open_pairs(data_root / "pairs" / "digit-hashgrid").manifest["preprocess"]
    width, height = SENSORS.build({"name": "digit"}).view_size()
    assert pre["crop_extent"] == "sensor" and pre["view_size"] == pytest.approx([width, height])
    assert (width, height) == pytest.approx((0.019053, 0.025403), abs=1e-6)  # 240 x 320 px, 60 deg, 22 mm


def test_too_many_novel_objects(data_root):
    make_inputs(data_root)
    with pytest.raises(TnfError, match="num_novel_objects=3"):
        run(compose("pair", ["debug=tiny", "progress=false", "pair.num_novel_objects=3"]))


def test_cli(data_root, capsys):
    from tnf.cli import main

    make_inputs(data_root, touches=2)
    assert main(["pair", *BASE]) == 0
    assert "paired dataset" in capsys.readouterr().out
    assert main(["pair", *BASE, "pair.crop_px=1000"]) == 1
    assert "larger than" in capsys.readouterr().err


def test_mesh_source_needs_no_fitted_scene(data_root):
    make_inputs(data_root, touches=3, scenes=False)
    build(["pair.scene_source=mesh"])
    a = open_pairs(data_root / "pairs" / "digit-mesh")
    assert a.manifest["scene_source"] == "mesh" and a.manifest["scene_checkpoints"] == {"ball": None, "box": None}
    assert len(a) == 6
    depth = a.depth.astype(np.float32)
    # The gel's footprint is the crop's central 1 / 1.5: 57 x 85 px (20 x 30 mm). Where a surface lies in it,
    # the nearest one (the first contact) is at 0.5; a coarser probe found it, hence the tolerance.
    footprint = depth[:, 64 - 42 : 64 + 42, 64 - 28 : 64 + 28].min(axis=(1, 2))
    hit = footprint < 1
    assert hit.any()  # the builtin objects lie in the footprint of (at least some) touches
    assert np.allclose(footprint[hit], 0.5, atol=0.02)


def test_pair_over_shards_renders_each_object_once_then_assembles_what_one_run_makes(data_root, tmp_path, capsys):
    # Jobs of a sweep over object shards render their own objects' caches; the run without shard assembles them.
    make_inputs(data_root)
    cache = data_root / "pairs" / ".cache" / "digit-hashgrid" / "builtin"
    build(["shard=1", "shards=2"])
    out = capsys.readouterr().out
    assert "rendering 6 touches of 1 object(s)" in out and "shard 1 of 2" in out
    assert sorted(p.name for p in cache.iterdir()) == ["box"]  # its share only, and no dataset yet
    assert not (data_root / "pairs" / "digit-hashgrid").exists()
    build(["shard=0", "shards=2"])
    assert "rendering 6 touches of 1 object(s)" in capsys.readouterr().out
    assert sorted(p.name for p in cache.iterdir()) == ["ball", "box"]
    build(["shard=0", "shards=2"])  # again: nothing left to render
    out = capsys.readouterr().out
    assert "rendering" not in out and "1 object(s) already rendered, 0 rendered now" in out
    build()
    assert "rendering" not in capsys.readouterr().out  # the caches are reused
    sharded = open_pairs(data_root / "pairs" / "digit-hashgrid")
    # The same dataset as one run over every object makes.
    other = tmp_path / "one-run"
    make_inputs(other)
    build([f"data_root={other}"])
    whole = open_pairs(other / "pairs" / "digit-hashgrid")
    assert sharded.manifest["objects"] == whole.manifest["objects"] == ["ball", "box"]
    assert sharded.manifest["counts"] == whole.manifest["counts"]
    for key in ("rgb", "depth", "tactile", "split", "object_id", "touch_index"):
        assert np.array_equal(np.asarray(getattr(sharded, key)), np.asarray(getattr(whole, key))), key
