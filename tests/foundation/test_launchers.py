"""Sweeps beyond one process: jobs of `-m` sweeps run in parallel by the Hydra launcher plugins (joblib;
submitit, locally here as there is no SLURM) share the artifact store without clobbering one another, and
the SLURM launcher's config composes with tnf's documented defaults."""

import multiprocessing
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tnf.artifacts import ArtifactStore, config_hash, read_json
from tnf.env import PRIMARY_CONFIG, conf_dir, stage_overrides

TINY = ["debug=tiny", "progress=false"]


def tnf(*args, root):
    env = {**os.environ, "TNF_DATA": str(root), "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-m", "tnf.cli", *args], capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    return out.stdout + out.stderr


def plugin(name):
    return pytest.importorskip(
        f"hydra_plugins.{name}", reason=f"needs {name.replace('_', '-')}: pip install 'tnf[launchers]'"
    )


def assert_complete_capture(root, objects):
    """Every object's capture item is finished, self-consistent and whole; nothing temporary is left."""
    store = ArtifactStore(root)
    assert store.items("capture", "builtin") == sorted(objects)
    for name in objects:
        item = store.path("capture", "builtin", name)
        manifest = read_json(item / "manifest.json")
        assert manifest["config_hash"] == config_hash(manifest["config"]) and manifest["object"] == name
        for split in ("transforms.json", "transforms_test.json"):
            frames = read_json(item / split)["frames"]
            assert frames
            for frame in frames:
                assert (item / frame["file_path"]).is_file() and (item / frame["depth_file_path"]).is_file()
        n_images = manifest["num_views"] + manifest["num_test_views"]
        assert len(list((item / "images").iterdir())) == n_images
    assert not [p for p in (root / "capture").rglob("*") if p.name.startswith(".")]


def _write_same_item(root, writer, barrier, errors):
    store = ArtifactStore(root)
    barrier.wait()
    for _ in range(25):
        try:
            with store.writing("capture", "builtin", "ball", config={"v": 1}, info={"writer": writer}) as tmp:
                for k in range(4):
                    (tmp / f"part{k}.txt").write_text(str(writer))
        except Exception as e:  # reported to the test, which expects none
            errors.put(repr(e))


def test_many_processes_writing_the_same_item_at_once_leave_one_whole_item(tmp_path):
    ctx = multiprocessing.get_context("fork")
    barrier, errors = ctx.Barrier(4), ctx.Queue()
    procs = [ctx.Process(target=_write_same_item, args=(tmp_path, w, barrier, errors)) for w in range(4)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
    assert [p.exitcode for p in procs] == [0, 0, 0, 0]
    assert errors.empty(), errors.get()
    item = ArtifactStore(tmp_path).path("capture", "builtin", "ball")
    # One writer's folder, all of it: its four parts and its manifest, nothing of another writer.
    writer = read_json(item / "manifest.json")["writer"]
    assert sorted(p.name for p in item.iterdir()) == ["manifest.json", *[f"part{k}.txt" for k in range(4)]]
    assert {(item / f"part{k}.txt").read_text() for k in range(4)} == {str(writer)}
    assert sorted(os.listdir(item.parent)) == ["ball"]


def test_joblib_sweep_captures_objects_in_parallel_jobs_one_item_twice(data_root):
    # Four jobs, two at a time; the first two both make capture/builtin/ball and may finish together.
    plugin("hydra_joblib_launcher")
    sweep = ["-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "object=ball,ball,box,can"]
    out = tnf("capture", *sweep, *TINY, root=data_root)
    assert "Joblib.Parallel(n_jobs=2" in out and "launching 4 jobs" in out
    assert_complete_capture(data_root, ["ball", "box", "can"])


def test_submitit_local_sweep(data_root):
    # The same plugin as hydra/launcher=submitit_slurm, with submitit's local executor: jobs are pickled and run
    # as separate processes, as on a cluster.
    plugin("hydra_submitit_launcher")
    out = tnf("capture", "-m", "hydra/launcher=submitit_local", *TINY, "object=ball,box", root=data_root)
    assert "Submitit 'local' sweep output dir" in out
    assert_complete_capture(data_root, ["ball", "box"])
    sweeps = list((data_root / "logs").rglob("multirun.yaml"))
    assert len(sweeps) == 1 and len(list((sweeps[0].parent / ".submitit").iterdir())) >= 2


def slurm_launcher(stage, overrides):
    """The launcher Hydra would instantiate for ``-m hydra/launcher=...`` (SLURM itself is not needed)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.utils import instantiate

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=conf_dir(), version_base=None):
        cfg = compose(config_name=PRIMARY_CONFIG, overrides=stage_overrides(stage, overrides), return_hydra_config=True)
    return cfg, instantiate(cfg.hydra.launcher)


@pytest.mark.parametrize("preset", ["submitit_slurm", "slurm"])
def test_slurm_launcher_config_composes(preset, data_root):
    plugin("hydra_submitit_launcher")
    cfg, launcher = slurm_launcher("train", [f"hydra/launcher={preset}", "trainer=ddp", "trainer.devices=4"])
    assert type(launcher).__name__ == "SlurmLauncher" and cfg.trainer.strategy == "ddp_spawn"
    assert launcher.params["submitit_folder"].startswith(str(data_root / "logs"))
    if preset == "slurm":  # tnf's defaults: one process and GPU per trainer device, requeue on time-out
        p = launcher.params
        assert (p["tasks_per_node"], p["gpus_per_node"], p["timeout_min"], p["max_num_timeout"]) == (4, 4, 240, 3)
        _, one = slurm_launcher("fit_scene", ["hydra/launcher=slurm", "hydra.launcher.partition=gpu"])
        assert (one.params["tasks_per_node"], one.params["gpus_per_node"], one.params["partition"]) == (1, 1, "gpu")


def test_slurm_preset_is_documented_and_shown_by_the_cli(data_root):
    plugin("hydra_submitit_launcher")
    lines = (Path(conf_dir()) / "hydra" / "launcher" / "slurm.yaml").read_text().splitlines()
    for i, line in enumerate(lines):
        if line and not line.startswith(("#", " ", "-", "defaults:")):
            assert lines[i - 1].startswith("#"), f"undocumented key: {line}"
    out = tnf("train", "hydra/launcher=slurm", "--cfg", "hydra", "-p", "hydra.launcher", root=data_root)
    assert "SlurmLauncher" in out and "tasks_per_node: ${trainer.devices}" in out and "max_num_timeout: 3" in out


SHARD_OBJECTS = ["ball", "box", "can", "mug"]
# Enough touches that one object takes a moment, so that the killed job below dies inside an item.
SHARD_TOUCH = [*TINY, f"object_names=[{','.join(SHARD_OBJECTS)}]", "touch.n_touches=60"]


def made_touch_items(out):
    """Objects whose touch item a run's output says it simulated, one entry per simulation."""
    return sorted(line.split("/")[-1].split(":")[0] for line in out.splitlines() if " touches, " in line)


def test_shards_split_the_objects_disjointly_and_cover_them():
    from tnf.errors import TnfError
    from tnf.objects import shard

    names = [f"o{i}" for i in range(10)]
    parts = [shard(names, i, 3) for i in range(3)]
    assert sorted(sum(parts, [])) == sorted(names) and [len(p) for p in parts] == [4, 3, 3]
    assert shard(names, None, 3) == names
    for bad in ((3, 3), (0, 0), ("x", 2)):
        with pytest.raises(TnfError, match="shard"):
            shard(names, *bad)


def test_joblib_sweep_over_shards_makes_each_object_once_and_redoes_a_killed_jobs_objects(data_root):
    import signal
    import time

    plugin("hydra_joblib_launcher")
    # A job of the sweep (shard 1 of 2: box and mug) killed while it writes its first item.
    env = {**os.environ, "TNF_DATA": str(data_root), "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "tnf.cli", "touch", "shards=2", "shard=1", *SHARD_TOUCH]
    job = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    items = data_root / "touch" / "digit" / "builtin"
    deadline = time.monotonic() + 300
    while not (items.is_dir() and any(p.name.endswith(".partial") for p in items.iterdir())):
        assert job.poll() is None, "the job ended before it was killed"
        assert time.monotonic() < deadline, "the job wrote no item in 300 s"
        time.sleep(0.01)
    job.send_signal(signal.SIGKILL)
    job.wait()
    store = ArtifactStore(data_root)
    done_before = set(store.items("touch", "digit", "builtin"))
    assert done_before < {"box", "mug"}  # the killed job left one of its objects unfinished, at least
    assert any(p.name.endswith(".partial") for p in items.iterdir())  # and its temporary folder behind

    # The sweep: two jobs at once, each simulates its shard's objects; the killed job's unfinished one is redone.
    sweep = ["-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "shards=2", "shard=0,1"]
    out = tnf("touch", *sweep, *SHARD_TOUCH, root=data_root)
    assert "launching 2 jobs" in out
    assert made_touch_items(out) == sorted(set(SHARD_OBJECTS) - done_before)  # each once, the finished ones not
    for name in done_before:
        assert f"touch digit/builtin/{name}: done, skipped" in out
    assert store.items("touch", "digit", "builtin") == sorted(SHARD_OBJECTS)
    for name in SHARD_OBJECTS:
        manifest = store.manifest("touch", "digit", "builtin", name)
        assert manifest is not None and manifest["object"] == name and len(manifest["touches"]) == 60 + 4 + 4
    assert not [p for p in items.iterdir() if p.name.startswith(".")]  # the killed job's leftovers are gone

    # The sweep again: every item is done, nothing is simulated.
    out = tnf("touch", *sweep, *SHARD_TOUCH, root=data_root)
    assert made_touch_items(out) == [] and out.count(": done, skipped") == len(SHARD_OBJECTS)
