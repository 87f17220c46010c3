"""The ``captured`` object source: a user's own camera images and tactile frames, imported and run through the
pipeline. The "user dataset" is made by running the real `tnf capture` and `tnf touch` on built-in objects and
writing their outputs in the user layout, shifted into another world frame (as a robot's base frame would be)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tnf.artifacts import ArtifactStore
from tnf.cameras import load_transforms, look_at
from tnf.cli import main
from tnf.data import open_pairs
from tnf.data.render import TouchItem
from tnf.errors import TnfError
from tnf.objects import select
from tnf.objects.captured import import_touches, import_views, start_pose, view_centre
from tnf.registry import OBJECTS, SENSORS
from tnf.testing import compose

TINY = ["debug=tiny", "progress=false", "device=cpu"]
OFFSET = np.array([0.4, -0.25, 0.1])  # where the user's frame puts the object's centre, metres
OBJECTS_ = ("ball", "box")


def _shift(m, offset=OFFSET) -> list:
    m = np.array(m, dtype=float)
    m[:3, 3] += offset
    return m.tolist()


def export_user_object(sim: Path, user: Path, obj: str, photos: bool) -> None:
    """Write the rendered capture and simulated touches of ``obj`` in the user layout under ``user/obj``.

    ``photos``: RGB JPEG images, no depth and no transforms_test.json (as a phone capture); else the RGBA PNGs,
    depth and the test views as they are.
    """
    cap, out = sim / "capture" / "builtin" / obj, user / obj
    (out / "images").mkdir(parents=True)
    splits = [("transforms.json", "train")] + ([] if photos else [("transforms_test.json", "test")])
    for file, split in splits:
        meta = json.loads((cap / file).read_text())
        for k, fr in enumerate(meta["frames"]):
            fr["transform_matrix"] = _shift(fr["transform_matrix"])
            src = cap / fr["file_path"]
            if photos:
                fr["file_path"] = f"./images/{split}_{k:04d}.jpg"
                Image.open(src).convert("RGB").save(out / fr["file_path"], quality=95)
                del fr["depth_file_path"]
            else:
                shutil.copy(src, out / fr["file_path"])
                (out / "depth").mkdir(exist_ok=True)
                shutil.copy(cap / fr["depth_file_path"], out / fr["depth_file_path"])
        (out / file).write_text(json.dumps(meta))
    touch = sim / "touch" / "digit" / "builtin" / obj
    info = json.loads((touch / "manifest.json").read_text())
    (out / "tactile" / "frames").mkdir(parents=True)
    shutil.copy(touch / "background.png", out / "tactile" / "background.png")
    entries = []
    for t in info["touches"]:
        rel = f"frames/{t['index']:04d}.png"
        shutil.copy(touch / t["image"], out / "tactile" / rel)
        entry = {"image": rel, "c2w": _shift(t["contact_c2w"])}
        if t["split"] != "train" or not photos:  # train is the default split
            entry["split"] = t["split"]
        entries.append(entry)
    (out / "tactile" / "touches.json").write_text(json.dumps(entries))


@pytest.fixture(scope="module")
def sim_and_user(tmp_path_factory):
    """(simulated data root, user dataset folder) for ball (PNG + depth + test views) and box (JPEG photos)."""
    base = tmp_path_factory.mktemp("captured")
    sim, user = base / "sim", base / "user"
    assert main(["capture", *TINY, f"data_root={sim}"]) == 0
    assert main(["touch", *TINY, f"data_root={sim}"]) == 0
    for obj in OBJECTS_:
        export_user_object(sim, user, obj, photos=obj == "box")
    return sim, user


def captured(user: Path, root: Path, *more: str) -> list[str]:
    return [*TINY, "objects=captured", f"objects.root={user}", f"data_root={root}", *more]


def import_all(user: Path, root: Path, cfg_overrides=()) -> None:
    """`tnf capture` on the user's objects, then their touches imported as `tnf touch` does."""
    assert main(["capture", *captured(user, root, *cfg_overrides)]) == 0
    cfg = compose("touch", captured(user, root, *cfg_overrides))
    source, names = select(cfg.objects, cfg.object_names, cfg.object)
    sensor = SENSORS.build(cfg.sensor)
    for name in names:
        import_touches(ArtifactStore(root), sensor, source, name, start_radius=float(cfg.touch.radius))


def test_import_reproduces_the_rendered_capture_and_touches(sim_and_user, tmp_path, capsys):
    sim, user = sim_and_user
    root = tmp_path / "data"
    import_all(user, root)
    for obj in OBJECTS_:
        ref = sim / "capture" / "builtin" / obj
        got = root / "capture" / "captured" / obj
        manifest = json.loads((got / "manifest.json").read_text())
        # The cameras look at the object's centre: recentring undoes the user's frame exactly.
        np.testing.assert_allclose(manifest["world_offset_m"], -OFFSET, atol=1e-5)
        images, c2w, k, w, h, depth = load_transforms(got)
        r_images, r_c2w, r_k, *_, r_depth = load_transforms(ref)
        assert k == pytest.approx(r_k) and (w, h) == (64, 64)
        if obj == "ball":  # PNG with alpha, depth and test views: copied exactly
            np.testing.assert_array_equal(images, r_images)
            np.testing.assert_allclose(c2w, r_c2w, atol=1e-5)
            np.testing.assert_array_equal(depth, r_depth)
            assert len(load_transforms(got / "transforms_test.json")[0]) == 4
        else:  # JPEG photos: opaque, no depth; frames 0, 8 held out as test views (objects.test_every=8)
            assert depth is None and (images[..., 3] == 255).all()
            keep = [i for i in range(16) if i % 8]
            np.testing.assert_allclose(c2w, r_c2w[keep], atol=1e-5)
            assert np.abs(images[..., :3].astype(int) - r_images[keep, ..., :3]).mean() < 3
            test = load_transforms(got / "transforms_test.json")
            np.testing.assert_allclose(test[1], r_c2w[[0, 8]], atol=1e-5)
        # Touches: same images and contact poses as simulated, starting on the touch.radius sphere.
        sim_t = json.loads((sim / "touch" / "digit" / "builtin" / obj / "manifest.json").read_text())
        got_t = json.loads((root / "touch" / "digit" / "captured" / obj / "manifest.json").read_text())
        assert got_t["sensor"] == sim_t["sensor"] and got_t["counts"]["train"] == sim_t["counts"]["train"]
        assert [t["split"] for t in got_t["touches"]] == [t["split"] for t in sim_t["touches"]]
        for a, b in zip(sim_t["touches"], got_t["touches"]):
            folder = root / "touch" / "digit" / "captured" / obj
            assert np.array_equal(
                np.asarray(Image.open(sim / "touch" / "digit" / "builtin" / obj / a["image"])),
                np.asarray(Image.open(folder / b["image"])),
            )
            np.testing.assert_allclose(b["contact_c2w"], a["contact_c2w"], atol=1e-6)
            # Simulated touches start on the touch.radius sphere and press along their axis: the import, which
            # moves the contact pose back onto that sphere, finds the same start pose (the camera pair renders).
            start = np.asarray(b["start_c2w"])
            np.testing.assert_allclose(start, a["start_c2w"], atol=1e-6)
            # The simulator's first contact lies on the gel: within its footprint around the gel's front centre
            # (sensor frame x, y; the tiny Digit's gel is 20 x 30 mm), and behind it by at most the gel's sag
            # (5 mm) plus the deepest indentation (3 mm).
            x, y, z = start[:3, :3].T @ np.subtract(a["contact_point"], b["contact_point"])
            assert abs(x) <= 0.0101 and abs(y) <= 0.0151 and -1e-4 <= z <= 0.0081, (x, y, z)
            assert b["force"] is None and b["penetration"] is None
    # Unchanged files: nothing is imported again.
    capsys.readouterr()
    assert main(["capture", *captured(user, root)]) == 0
    assert capsys.readouterr().out.count("skipped (done)") == 2


@pytest.mark.slow
def test_fit_scene_and_pair_run_on_imported_photos(sim_and_user, tmp_path):
    """The box's views are JPEG photos without depth or test file: fit-scene and pair run on them as they are."""
    sim, user = sim_and_user
    root = tmp_path / "data"
    import_all(user, root)
    one = ("object=box", "pair.num_novel_objects=0")
    # Few steps and small renders: the scene only needs to exist (its quality is the scene tests' business).
    assert main(["fit-scene", *captured(user, root, *one, "fit.steps=40", "fit.eval_views=1")]) == 0
    metrics = json.loads((root / "scenes" / "hashgrid" / "captured" / "box" / "metrics.json").read_text())
    assert metrics["psnr"] > 8 and metrics["test_views"] == 1 and metrics["train_views"] == 14
    assert not any(k.startswith("depth_error") for k in metrics)  # no depth given, none measured
    assert main(["pair", *captured(user, root, *one, "pair.render_px=24")]) == 0
    manifest = json.loads((root / "pairs" / "digit-hashgrid" / "manifest.json").read_text())
    assert manifest["counts_per_object"] == {"box": 20} and manifest["object_source"]["name"] == "captured"
    counts = json.loads((root / "touch" / "digit" / "captured" / "box" / "manifest.json").read_text())["counts"]
    assert manifest["counts"] == {
        "train": counts["train"],
        "val": counts["val"],
        "novel_view": counts["novel_view"],
        "novel_object": 0,
    }
    # The real tactile images, in touch order (the pairs' RGB-D is only as good as a 40-step scene).
    pairs = open_pairs(root / "pairs" / "digit-hashgrid")
    real = TouchItem.load(sim / "touch" / "digit" / "builtin" / "box").tactile(range(20))
    np.testing.assert_array_equal(np.asarray(pairs.tactile)[np.argsort(pairs.touch_index)], real)


@pytest.mark.slow
def test_pipeline_on_imported_data(sim_and_user, tmp_path):
    _, user = sim_and_user
    root = tmp_path / "data"
    import_all(user, root)
    stages = "pipeline.stages=[capture,fit-scene,touch,pair,train,generate,evaluate]"  # touch: already imported
    assert main(["pipeline", *captured(user, root, "experiment=real_capture", stages, "pair.render_px=32")]) == 0
    reports = root / "reports" / "tiny"  # debug=tiny's report, apart from the experiment's
    model = json.loads(next((reports / "timings").glob("*.json")).read_text())["model"]
    for obj in OBJECTS_:  # tactile images generated from novel poses of both objects
        generated = json.loads((root / "generated" / model / "captured" / obj / "manifest.json").read_text())
        assert len(generated["touches"]) == 4 and (root / "generated" / model / "captured" / obj / "images").is_dir()
    report = reports / "report.md"
    assert report.is_file() and "T-N" in report.read_text()


# -- hand-made datasets for the error cases ----------------------------------------------------------------
def small_dataset(root: Path, obj: str = "cube", sensor_size=(60, 80)) -> Path:
    """``root/obj``: 6 camera views (16 px) looking at (0.2, 0, 0) and 3 touches of the tiny Digit."""
    folder = root / obj
    (folder / "images").mkdir(parents=True)
    frames = []
    for i, d in enumerate(np.eye(3).tolist() + (-np.eye(3)).tolist()):
        centre = np.array([0.2, 0.0, 0.0])
        m = look_at(centre + 0.3 * np.asarray(d) + [0, 0.01, 0.02], centre)
        Image.fromarray(np.full((16, 16, 3), 40 * i, np.uint8)).save(folder / "images" / f"{i}.png")
        frames.append({"file_path": f"images/{i}.png", "transform_matrix": m.tolist()})
    meta = {"fl_x": 20.0, "fl_y": 20.0, "cx": 8, "cy": 8, "w": 16, "h": 16, "frames": frames}
    (folder / "transforms.json").write_text(json.dumps(meta))
    tactile = folder / "tactile"
    tactile.mkdir()
    w, h = sensor_size
    Image.fromarray(np.full((h, w, 3), 100, np.uint8)).save(tactile / "background.png")
    touches = []
    for i in range(3):
        Image.fromarray(np.full((h, w, 3), 120 + i, np.uint8)).save(tactile / f"t{i}.png")
        pose = look_at([0.2 + 0.05, 0.01 * i, 0.0], [0.2, 0.0, 0.0])
        touches.append({"image": f"t{i}.png", "c2w": pose.tolist(), "split": ["train", "val", "novel_view"][i]})
    (tactile / "touches.json").write_text(json.dumps(touches))
    return folder


def touch_cfg(user: Path, root: Path):
    cfg = compose("touch", captured(user, root, "object=cube"))
    source, _ = select(cfg.objects, single=cfg.object)
    return source, SENSORS.build(cfg.sensor)


def test_small_dataset_imports(tmp_path):
    user, root = tmp_path / "user", tmp_path / "data"
    small_dataset(user)
    assert main(["capture", *captured(user, root, "object=cube", "objects.test_every=3")]) == 0
    meta = json.loads((root / "capture" / "captured" / "cube" / "transforms.json").read_text())
    assert [f["source_frame"] for f in meta["frames"]] == [1, 2, 4, 5]
    # fit-scene on views without depth: PSNR and SSIM on the held-out views, no depth error.
    assert main(["fit-scene", *captured(user, root, "object=cube", "fit.steps=2", "fit.eval_views=1")]) == 0
    metrics = json.loads((root / "scenes" / "hashgrid" / "captured" / "cube" / "metrics.json").read_text())
    assert metrics["test_views"] == 1 and np.isfinite(metrics["psnr"]) and 0 < metrics["ssim"] <= 1
    assert not any(k.startswith("depth_error") for k in metrics)
    source, sensor = touch_cfg(user, root)
    msg = import_touches(ArtifactStore(root), sensor, source, "cube", start_radius=0.15)
    assert "3 touches imported" in msg
    info = json.loads((root / "touch" / "digit" / "captured" / "cube" / "manifest.json").read_text())
    assert info["counts"] == {
        "train": 1,
        "val": 1,
        "novel_view": 1,
        "discarded": {"train": 0, "val": 0, "novel_view": 0},
    }
    # The world moved by -(0.2, 0, 0): the first touch presses from +x, 5 cm out from the object's centre.
    np.testing.assert_allclose(np.asarray(info["touches"][0]["contact_c2w"])[:3, 3], [0.05, 0, 0], atol=1e-6)
    assert import_touches(ArtifactStore(root), sensor, source, "cube", start_radius=0.15).endswith("skipped")


def test_view_centre_and_start_pose():
    poses = np.stack([look_at(np.array([0.1, 0.2, 0.3]) + 0.5 * d, [0.1, 0.2, 0.3]) for d in np.eye(3)])
    np.testing.assert_allclose(view_centre(poses), [0.1, 0.2, 0.3], atol=1e-9)
    with pytest.raises(TnfError, match="parallel"):
        view_centre(np.stack([np.eye(4), np.eye(4)]))
    start = start_pose(look_at([0.0, 0.0, 0.05], [0, 0, 0]), 0.15)
    assert start is not None
    np.testing.assert_allclose(start[:3, 3], [0, 0, 0.15], atol=1e-12)
    assert start_pose(look_at([0.0, 0.0, 0.2], [0, 0, 0]), 0.15) is None


def _error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err  # one line
    return err


def test_missing_transforms_or_image_fails_and_writes_nothing(tmp_path, capsys):
    user, root = tmp_path / "user", tmp_path / "data"
    folder = small_dataset(user)
    (folder / "transforms.json").rename(folder / "other.json")
    capsys.readouterr()
    assert main(["capture", *captured(user, root, "object=cube")]) == 1
    assert f"transforms file not found: {folder / 'transforms.json'}" in _error(capsys)
    (folder / "other.json").rename(folder / "transforms.json")
    (folder / "images" / "3.png").unlink()
    assert main(["capture", *captured(user, root, "object=cube")]) == 1
    assert f"frame 3 image not found: {folder / 'images' / '3.png'}" in _error(capsys)
    assert not (root / "capture" / "captured" / "cube").exists()
    assert not list((root / "capture").rglob("*.png"))


def test_root_is_required_and_there_are_no_meshes(tmp_path, capsys):
    with pytest.raises(TnfError, match=r"objects.captured: root is required"):
        OBJECTS.build({"name": "captured"})
    capsys.readouterr()
    assert main(["capture", *TINY, "objects=captured", f"data_root={tmp_path}"]) == 1
    assert "root is required" in _error(capsys)
    user = tmp_path / "user"
    small_dataset(user)
    source = OBJECTS.build({"name": "captured", "root": str(user)})
    assert source.names() == ["cube"]
    with pytest.raises(TnfError, match="has camera images, not meshes"):
        source.load("cube")
    # The tiny config's objects (ball, box) are not in the folder.
    assert main(["capture", *captured(user, tmp_path / "data")]) == 1
    assert "unknown object 'ball' in source 'captured'; available: cube" in _error(capsys)
    shutil.rmtree(user / "cube" / "tactile")
    with pytest.raises(TnfError, match=r"tactile frames not found: .*cube/tactile/touches.json"):
        source.touches("cube")


@pytest.mark.parametrize(
    "case, match",
    [
        (
            "size",
            r"t1.png: tactile image is 80x60 pixels, expected 60x80 \(sensor.width x sensor.height of sensor 'digit'\)",
        ),
        ("background", r"background.png: the background is 60x60 pixels, expected 60x80"),
        ("shape", r"touches.json: touch 2 c2w has shape \[3, 4\], expected \[4, 4\]"),
        ("rigid", r"touches.json: touch 0 c2w is not a rigid transform"),
        ("split", r"touches.json: touch 1 split must be one of train, val, novel_view, got 'test'"),
        ("key", r"touches.json: touch 0 has unknown key 'spilt'"),
        ("missing", r"touches.json: touch 1 image not found: .*t9.png"),
        ("far", r"touches.json: touch 0: the sensor is 0.250 m from the object's centre, not inside touch.radius"),
        ("json", r"touches file .*touches.json is not valid JSON"),
    ],
)
def test_bad_tactile_input_fails_and_writes_nothing(tmp_path, case, match):
    user, root = tmp_path / "user", tmp_path / "data"
    tactile = small_dataset(user) / "tactile"
    source = OBJECTS.build({"name": "captured", "root": str(user)})
    sensor = SENSORS.build({"name": "digit", "width": 60, "height": 80})
    import_views(ArtifactStore(root), source, "cube")
    touches = json.loads((tactile / "touches.json").read_text())
    if case == "size":
        Image.fromarray(np.zeros((60, 80, 3), np.uint8)).save(tactile / "t1.png")
    elif case == "background":
        Image.fromarray(np.zeros((60, 60, 3), np.uint8)).save(tactile / "background.png")
    elif case == "shape":
        touches[2]["c2w"] = touches[2]["c2w"][:3]
    elif case == "rigid":
        touches[0]["c2w"][0][0] = 2.0
    elif case == "split":
        touches[1]["split"] = "test"
    elif case == "key":
        touches[0]["spilt"] = touches[0].pop("split")
    elif case == "missing":
        touches[1]["image"] = "t9.png"
    elif case == "far":
        touches[0]["c2w"] = look_at([0.45, 0.0, 0.0], [0.2, 0.0, 0.0]).tolist()
    (tactile / "touches.json").write_text("[{" if case == "json" else json.dumps(touches))
    with pytest.raises(TnfError, match=match) as e:
        import_touches(ArtifactStore(root), sensor, source, "cube", start_radius=0.15)
    assert "\n" not in str(e.value)
    assert not (root / "touch").exists() or not list((root / "touch").rglob("*.png"))


def test_touches_need_the_imported_capture(tmp_path):
    user, root = tmp_path / "user", tmp_path / "data"
    small_dataset(user)
    source, sensor = touch_cfg(user, root)
    with pytest.raises(TnfError, match=r"missing capture output .*; run `tnf capture object=cube` first"):
        import_touches(ArtifactStore(root), sensor, source, "cube", start_radius=0.15)
