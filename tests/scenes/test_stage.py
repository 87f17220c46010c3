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


@pytest.mark.parametrize("together", [1, 2])
def test_train_kernel_setting_trains_by_the_warp_kernels(data_root, monkeypatch, together):
    """``fit.train_kernel=true``: each training step's encoding goes through the Warp kernels (one object alone and
    two batched), the scenes' keys record the setting, and a fit without it keeps the keys it had."""
    from tnf.scenes import hash_kernel

    calls = []
    real = hash_kernel.hash_encode_trainable
    monkeypatch.setattr(hash_kernel, "hash_encode_trainable", lambda *a, **k: calls.append(1) or real(*a, **k))
    for name in ("a", "b"):
        _capture(data_root, name)
    base = [*OVERRIDES, "object_names=[a,b]", f"fit.batch_objects={together}"]
    rows = fit_scene.run(compose("fit-scene", [*base, "fit.train_kernel=true"]))
    assert [r["status"] for r in rows] == ["fitted", "fitted"]
    assert len(calls) >= 30  # every training step of the 30 (evaluation renders with the rendering kernel)
    for name in ("a", "b"):
        manifest = json.loads((data_root / "scenes" / "hashgrid" / "builtin" / name / "manifest.json").read_text())
        assert manifest["config"]["fit"]["train_kernel"] is True
    calls.clear()
    rows = fit_scene.run(compose("fit-scene", base))
    assert [r["status"] for r in rows] == ["fitted", "fitted"] and calls == []
    manifest = json.loads((data_root / "scenes" / "hashgrid" / "builtin" / "a" / "manifest.json").read_text())
    assert "train_kernel" not in manifest["config"]["fit"]


def test_a_nerf_fits_without_the_hash_grids_speed_ups_and_with_its_usual_key(data_root, caplog):
    """The quick start and sim_digit set fit.train_kernel and fit.batch_objects; scene=nerf still fits."""
    _capture(data_root, "sphere")
    nerf = [*OVERRIDES, "object=sphere", "scene=nerf", "fit.steps=2"]
    with caplog.at_level("WARNING", logger="tnf.stages.fit_scene"):
        rows = fit_scene.run(compose("fit-scene", [*nerf, "fit.train_kernel=true", "fit.batch_objects=4"]))
    assert [r["status"] for r in rows] == ["fitted"]
    assert "speed up hashgrid scenes only: nerf scenes fit one at a time" in caplog.text
    manifest = json.loads((data_root / "scenes" / "nerf" / "builtin" / "sphere" / "manifest.json").read_text())
    assert "train_kernel" not in manifest["config"]["fit"] and "batch_objects" not in manifest["config"]["fit"]
    # Without the settings: the same key, so the fit is found done.
    assert [r["status"] for r in fit_scene.run(compose("fit-scene", nerf))] == ["skipped (done)"]
