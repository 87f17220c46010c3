"""``fit.workers``: fit-scene's objects fitted in worker processes on this machine (``tnf.stages.local_workers``),
each worker as the job ``shard=i shards=N`` of a sweep over shards; real fits of captured spheres on the CPU."""

import json
import subprocess
import sys
import time

import pytest
import torch

from tnf.artifacts import ArtifactStore, identity
from tnf.errors import TnfError
from tnf.scenes.synthetic import write_sphere_dataset
from tnf.scenes.system import FitSettings
from tnf.stages import fit_scene
from tnf.stages.local_workers import StepFile, _stop, worker_warnings
from tnf.testing import compose

OVERRIDES = [
    "debug=tiny",
    "progress=false",
    "device=cpu",
    "fit.steps=5",
    "fit.batch_rays=64",
    "fit.eval_views=1",
    "fit.preview_views=1",
    "object_names=null",
]


RADII = {"a": 0.05, "b": 0.04, "c": 0.03}


def _capture(root, name):
    store = ArtifactStore(root)
    with store.writing("capture", "builtin", name, config={"test": name}, info={"radius_m": 0.05}) as tmp:
        write_sphere_dataset(tmp, n_train=4, n_test=1, size=12, radius=RADII[name])


def _scene(root, name):
    return torch.load(root / "scenes" / "hashgrid" / "builtin" / name / "scene.pt", weights_only=False)


def _manifest(root, name):
    return json.loads((root / "scenes" / "hashgrid" / "builtin" / name / "manifest.json").read_text())


def _tensors(state):
    """Every tensor of a saved scene, by its path in the nested dicts."""
    out = {}

    def walk(x, path):
        if isinstance(x, torch.Tensor):
            out[path] = x
        elif isinstance(x, dict):
            for k, v in x.items():
                walk(v, f"{path}/{k}")

    walk(state, "")
    return out


def test_workers_fit_each_share_as_its_job_of_a_sweep_over_shards(tmp_path, monkeypatch):
    """Two workers over three objects (two batched in worker 1): the same scenes as the jobs ``shard=0`` and
    ``shard=1`` of ``shards=2`` run one after the other, under the same keys, so a rerun without workers skips
    them."""
    roots = {"workers": tmp_path / "workers", "shards": tmp_path / "shards"}
    for root in roots.values():
        for name in ("a", "b", "c"):
            _capture(root, name)
    base = [*OVERRIDES, "fit.batch_objects=2"]
    monkeypatch.setenv("TNF_DATA", str(roots["workers"]))
    rows = fit_scene.run(compose("fit-scene", [*base, "fit.workers=2"]))
    assert [(r["object"], r["status"]) for r in rows] == [("a", "fitted"), ("b", "fitted"), ("c", "fitted")]
    assert [r["batch_objects"] for r in rows] == [2, 1, 2]  # worker 1: a and c together; worker 2: b alone

    monkeypatch.setenv("TNF_DATA", str(roots["shards"]))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as each worker of two on a machine of up to 3 cores
    try:
        for i in (0, 1):
            fit_scene.run(compose("fit-scene", [*base, f"shard={i}", "shards=2"]))
    finally:
        torch.set_num_threads(threads)
    for name in ("a", "b", "c"):
        assert _manifest(roots["workers"], name)["config_hash"] == _manifest(roots["shards"], name)["config_hash"]
        ours, theirs = _tensors(_scene(roots["workers"], name)), _tensors(_scene(roots["shards"], name))
        assert ours.keys() == theirs.keys() and ours
        for k in ours:
            torch.testing.assert_close(ours[k], theirs[k], atol=1e-5, rtol=1e-4, msg=f"{name} {k}")

    monkeypatch.setenv("TNF_DATA", str(roots["workers"]))
    rows = fit_scene.run(compose("fit-scene", [*base, "fit.workers=1"]))
    assert {r["status"] for r in rows} == {"skipped (done)"}


def test_workers_fit_only_what_is_left_and_one_share_left_fits_in_this_process(data_root, monkeypatch):
    """Objects already fitted are not given to any worker; a single share left to fit is fitted here, with no
    worker process."""
    for name in ("a", "b"):
        _capture(data_root, name)
    fit_scene.run(compose("fit-scene", [*OVERRIDES, "object=a"]))
    started = []
    monkeypatch.setattr(subprocess, "Popen", lambda *a, **k: started.append(a) or pytest.fail("a worker started"))
    rows = fit_scene.run(compose("fit-scene", [*OVERRIDES, "fit.workers=2"]))
    assert [(r["object"], r["status"]) for r in rows] == [("a", "skipped (done)"), ("b", "fitted")]
    assert not started


def test_objects_done_before_are_listed_once_when_workers_fit_the_rest(data_root):
    """a is done; b and c go to two workers (a and c share worker 1): each object is one row of the result."""
    for name in ("a", "b", "c"):
        _capture(data_root, name)
    fit_scene.run(compose("fit-scene", [*OVERRIDES, "object=a"]))
    rows = fit_scene.run(compose("fit-scene", [*OVERRIDES, "fit.workers=2"]))
    assert [(r["object"], r["status"]) for r in rows] == [("a", "skipped (done)"), ("b", "fitted"), ("c", "fitted")]


def test_a_failing_worker_is_one_error_naming_it_and_its_objects(data_root):
    """A capture whose views cannot be read fails its worker; the other worker's object is fitted, and the error
    names the failed worker, its objects and the last lines it wrote."""
    for name in ("a", "b"):
        _capture(data_root, name)
    (data_root / "capture" / "builtin" / "b" / "transforms.json").write_text("{ not json")
    with pytest.raises(TnfError, match=r"fit-scene in 2 worker processes: fit hashgrid 2/2 \(b\) exited 1: "):
        fit_scene.run(compose("fit-scene", [*OVERRIDES, "fit.workers=2"]))
    assert (data_root / "scenes" / "hashgrid" / "builtin" / "a" / "scene.pt").is_file()
    assert not (data_root / "scenes" / "hashgrid" / "builtin" / "b").exists()


def test_workers_setting_is_checked_and_out_of_the_scenes_identity():
    assert "workers" not in identity(FitSettings(workers=4))
    with pytest.raises(ValueError, match="workers"):
        FitSettings(workers=0).validate()


def test_step_file_writes_the_steps_done_over_every_task(tmp_path):
    path = tmp_path / "progress"
    p = StepFile(path, every=3600)
    a = p.add_task("a", total=10)
    b = p.add_task("b", total=4)
    p.update(a, completed=3)  # the first write comes at once
    assert float(path.read_text()) == 3
    p.update(a, completed=5)  # within `every` of the last: not written
    assert float(path.read_text()) == 3
    p.update(a, completed=10)  # a task's end is always written
    assert float(path.read_text()) == 10
    p.advance(b)
    p.update(b, completed=4)
    assert float(path.read_text()) == 14


def test_stop_ends_workers_still_running():
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    t0 = time.monotonic()
    _stop([proc], grace=5)
    assert proc.returncode is not None and time.monotonic() - t0 < 5


def test_a_warning_every_worker_logs_is_shown_once_naming_them_all():
    line = "[2026-12-08 01:00:00,000][tnf.scenes.fit][WARNING] - {}"
    logs = [
        "\n".join([line.format("fit.batch_objects groups hash grids only"), "[..][x][INFO] - fitted a"]),
        "\n".join([line.format("fit.batch_objects groups hash grids only"), line.format("object c: few views")]),
    ]
    assert worker_warnings(["1/2", "2/2"], logs) == [
        "workers 1/2, 2/2: fit.batch_objects groups hash grids only",
        "worker 2/2: object c: few views",
    ]
