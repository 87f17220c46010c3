"""A scene fit resumes only from a checkpoint made from the same inputs (captured images, scene settings), one
object alone and a batched group; settings that do not change the fitted scene are no part of its key."""

import shutil

import pytest

from tests.scenes.stops import Stop, stop_at
from tests.scenes.test_fit import TINY
from tests.scenes.test_stage import OVERRIDES
from tnf.artifacts import ArtifactStore, identity
from tnf.scenes.batched import fit_objects
from tnf.scenes.fit import fit_object
from tnf.scenes.synthetic import write_sphere_dataset
from tnf.scenes.system import FitSettings
from tnf.stages import fit_scene
from tnf.testing import compose

# Checkpoints after steps 4 and 9; a fit stopped at step 7 resumes at step 5.
SETTINGS = FitSettings(steps=12, batch_rays=64, checkpoint_every=5, log_every=4, eval_views=1, preview_views=1)


def _capture(root, name, config, radius=0.05, manifest=True):
    """A capture item of an analytic sphere (``radius`` metres; the number of rays does not depend on it) made with
    ``config``, as ``tnf capture`` leaves it; or, without ``manifest``, a bare capture-format folder."""
    if not manifest:
        folder = root / "bare" / name
        shutil.rmtree(folder, ignore_errors=True)
        return write_sphere_dataset(folder, n_train=6, n_test=1, size=16, radius=radius)
    store = ArtifactStore(root)
    with store.writing("capture", "builtin", name, config=config, info={"radius_m": radius}) as tmp:
        write_sphere_dataset(tmp, n_train=6, n_test=1, size=16, radius=radius)
    return store.path("capture", "builtin", name)


def _fit(capture, out, resume, spec=TINY, on_step=None):
    steps = []

    def record(step, loss):
        steps.append(step)
        if on_step is not None:
            on_step(step, loss)

    fit_object(spec, capture, out, SETTINGS, resume_path=resume, on_step=record, seed=3)
    return steps


@pytest.mark.parametrize("manifest", [True, False], ids=["capture-item", "bare-folder"])
def test_a_checkpoint_of_other_captured_images_is_not_resumed_from(tmp_path, caplog, manifest):
    resume = tmp_path / "resume" / "sphere.pt"
    capture = _capture(tmp_path, "sphere", {"ambient": 0.3}, manifest=manifest)
    with pytest.raises(Stop):
        _fit(capture, tmp_path / "out", resume, on_step=stop_at(7))
    assert resume.is_file()
    # Captured again with other settings: other images of the same size (the same rays, the same tensor shapes).
    capture = _capture(tmp_path, "sphere", {"ambient": 0.9}, radius=0.035, manifest=manifest)
    with caplog.at_level("WARNING", logger="tnf.scenes.fit"):
        steps = _fit(capture, tmp_path / "out", resume)
    assert steps == list(range(12))  # from step 0, not from the checkpoint of step 4
    lines = [r.getMessage() for r in caplog.records if "not resuming" in r.getMessage()]
    assert len(lines) == 1 and "(made from other captured images): the fit starts afresh" in lines[0], lines
    assert not resume.exists()
    # A checkpoint of these images: resumed.
    with pytest.raises(Stop):
        _fit(capture, tmp_path / "out", resume, on_step=stop_at(7))
    caplog.clear()
    with caplog.at_level("WARNING", logger="tnf.scenes.fit"):
        assert _fit(capture, tmp_path / "out", resume) == list(range(5, 12))
    assert "not resuming" not in caplog.text and not resume.exists()


def test_a_checkpoint_of_other_scene_settings_is_not_resumed_from(tmp_path, caplog):
    resume = tmp_path / "resume.pt"
    capture = _capture(tmp_path, "sphere", {"ambient": 0.3})
    with pytest.raises(Stop):
        _fit(capture, tmp_path / "out", resume, on_step=stop_at(7))
    # A finer march: the scene's tensors keep their shapes, its training does not.
    with caplog.at_level("WARNING", logger="tnf.scenes.fit"):
        steps = _fit(capture, tmp_path / "out", resume, spec={**TINY, "samples_per_ray": 64})
    assert steps == list(range(12))
    assert "(made with other scene settings): the fit starts afresh" in caplog.text


def _fit_group(captures, outs, resume, on_step=None):
    steps = []

    def record(step, loss):
        steps.append(step)
        if on_step is not None:
            on_step(step, loss)

    fit_objects([TINY] * 2, captures, outs, SETTINGS, resume_path=resume, on_step=record, seed=3, names=["a", "b"])
    return steps


def test_a_group_checkpoint_of_other_captured_images_is_not_resumed_from(tmp_path, caplog):
    resume = tmp_path / "group.pt"
    outs = [tmp_path / "out-a", tmp_path / "out-b"]
    captures = [_capture(tmp_path, "a", {"ambient": 0.3}), _capture(tmp_path, "b", {"ambient": 0.3})]
    with pytest.raises(Stop):
        _fit_group(captures, outs, resume, on_step=stop_at(7))
    assert resume.is_file()
    captures[1] = _capture(tmp_path, "b", {"ambient": 0.9}, radius=0.035)
    with caplog.at_level("WARNING", logger="tnf.scenes.batched"):
        steps = _fit_group(captures, outs, resume)
    assert steps == list(range(12))
    assert "(made from other captured images of b): the batched fit starts afresh" in caplog.text
    assert not resume.exists()
    # The same inputs: resumed.
    with pytest.raises(Stop):
        _fit_group(captures, outs, resume, on_step=stop_at(7))
    caplog.clear()
    with caplog.at_level("WARNING", logger="tnf.scenes.batched"):
        assert _fit_group(captures, outs, resume) == list(range(5, 12))
    assert "not resuming" not in caplog.text


def test_settings_that_do_not_change_the_scene_are_no_part_of_its_key():
    key = identity(FitSettings())
    assert not {"checkpoint_every", "chunk", "log_every"} & key.keys()
    assert {"eval_views", "preview_views", "steps"} <= key.keys()  # they change what is recorded


def test_changing_checkpoint_every_chunk_or_log_every_leaves_the_scene_done(data_root):
    _capture(data_root, "sphere", {"test": "sphere"})
    base = [*OVERRIDES, "object=sphere", "fit.steps=10"]
    assert [r["status"] for r in fit_scene.run(compose("fit-scene", base))] == ["fitted"]
    for more in (["fit.checkpoint_every=3"], ["fit.chunk=100"], ["fit.log_every=2"]):
        rows = fit_scene.run(compose("fit-scene", [*base, *more]))
        assert [r["status"] for r in rows] == ["skipped (done)"], more
