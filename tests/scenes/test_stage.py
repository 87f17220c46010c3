"""``tnf fit-scene`` end to end on a captured analytic sphere (real config, tiny settings)."""

import json

import pytest

from tnf.artifacts import ArtifactStore
from tnf.errors import TnfError
from tnf.scenes import load_scene
from tnf.scenes.synthetic import write_sphere_dataset
from tnf.stages import fit_scene
from tnf.testing import compose

OVERRIDES = ["debug=tiny", "progress=false", "device=cpu", "fit.steps=30", "fit.batch_rays=128", "fit.eval_views=1"]


def _capture(root, name):
    store = ArtifactStore(root)
    with store.writing("capture", "builtin", name, config={"test": name}, info={"radius_m": 0.05}) as tmp:
        write_sphere_dataset(tmp, n_train=6, n_test=1, size=16)


def test_fit_scene_writes_the_item_and_skips_it_when_done(data_root):
    _capture(data_root, "sphere")
    cfg = compose("fit-scene", [*OVERRIDES, "object=sphere"])
    rows = fit_scene.run(cfg)
    assert [r["status"] for r in rows] == ["fitted"]
    item = data_root / "scenes" / "hashgrid" / "builtin" / "sphere"
    for f in ("scene.pt", "metrics.json", "preview.png", "manifest.json"):
        assert (item / f).is_file(), f
    metrics = json.loads((item / "metrics.json").read_text())
    assert metrics["steps"] == 30 and metrics["test_views"] == 1
    assert metrics["bound_m"] == pytest.approx(0.051)  # from the capture's object radius
    scene = load_scene(item)
    assert scene.cfg.levels == cfg.scene.levels
    assert not (data_root / "scenes" / ".resume" / "hashgrid" / "builtin" / "sphere.pt").exists()
    # Same settings: skipped. Other settings: fitted again.
    assert [r["status"] for r in fit_scene.run(cfg)] == ["skipped (done)"]
    cfg2 = compose("fit-scene", [*OVERRIDES, "object=sphere", "fit.steps=20"])
    assert [r["status"] for r in fit_scene.run(cfg2)] == ["fitted"]


def test_fits_every_captured_object_when_none_is_named(data_root):
    _capture(data_root, "a")
    _capture(data_root, "b")
    cfg = compose("fit-scene", [*OVERRIDES, "fit.steps=5", "object_names=null"])
    rows = fit_scene.run(cfg)
    assert [(r["object"], r["status"]) for r in rows] == [("a", "fitted"), ("b", "fitted")]


def test_missing_capture_says_to_run_capture(data_root):
    cfg = compose("fit-scene", [*OVERRIDES, "object=nothing"])
    with pytest.raises(TnfError, match="tnf capture"):
        fit_scene.run(cfg)


def test_bad_scene_setting_is_named(data_root):
    _capture(data_root, "sphere")
    cfg = compose("fit-scene", [*OVERRIDES, "object=sphere", "scene.levels=0"])
    with pytest.raises(TnfError, match="levels"):
        fit_scene.run(cfg)
