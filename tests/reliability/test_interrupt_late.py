"""The late stages (`tnf finetune`, `tnf generate`, `tnf evaluate`, `tnf pipeline`) killed part-way (SIGKILL) and
run again: the result is the one of an uninterrupted run, finished items are not redone, and a half-written item
or checkpoint is never taken for a finished one.

Every input comes from the real commands: one tiny pipeline run (capture, fit-scene, touch, pair, train) makes
the store that the tests copy from. The uninterrupted runs the killed ones are compared with: the whole pipeline
(for generate, evaluate and pipeline: the stand-alone commands are given the settings the pipeline gives them)
and one fine-tuning run. The default run kills each stage once; the tests marked slow kill at further points.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.generators.test_stages import model_of
from tests.reliability.helpers import (
    assert_not_rewritten,
    copy_stages,
    finished_items,
    kill_when,
    leftovers,
    manifest_stamps,
    run_to_end,
    same_arrays,
    tree_bytes,
)

# The quick-start experiment at debug size; scenes fitted for a few steps and pairs rendered from the meshes,
# so that the whole store is made in seconds.
TINY = (
    "experiment=quickstart",
    "debug=tiny",
    "progress=false",
    "fit.steps=30",
    "fit.eval_views=1",
    "fit.preview_views=1",
    "pair.scene_source=mesh",
    # A run id ends in the hash of its datasets' content, unknown before the store exists: the model is named.
    "train.run_name=late-tn",
)
DATASET = "digit-mesh"
UPSTREAM = ("capture", "scenes", "touch", "pairs", "models")
# Several batches per object, so that a kill can land between two of them.
GENERATE_SIZE = ("generate.n_poses=8", "generate.batch_size=2")
PIPELINE = ("pipeline", *TINY, *GENERATE_SIZE)
MODEL = model_of(*PIPELINE)  # the pipeline's model (train.run_name above), trained on DATASET
# What the pipeline gives the generate and evaluate stages, on the command line.
GENERATE = ("generate", *TINY, *GENERATE_SIZE, f"generate.model={MODEL}")
EVALUATE = (
    "evaluate",
    *TINY,
    *GENERATE_SIZE,
    f"generate.model={MODEL}",
    f"evaluate.model={MODEL}",
    f"evaluate.generated={MODEL}",
    f"evaluate.dataset={DATASET}",
)
GENERATED = Path("generated") / MODEL / "builtin"
REPORT = Path("reports") / "tiny"
RESULTS = REPORT / "runs" / "main_T-N_seed0" / "results.json"


def manifest(folder: Path) -> dict:
    return json.loads((folder / "manifest.json").read_text())


def ckpt(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)


def ckpt_epoch_at_least(path: Path, epoch: int):
    """A kill condition: ``path`` holds a checkpoint written after epoch ``epoch`` (0-based)."""

    def ready() -> bool:
        if not path.is_file():
            return False
        try:
            return ckpt(path)["epoch"] >= epoch
        except Exception:  # being replaced right now
            return False

    return ready


def said(out: subprocess.CompletedProcess, text: str) -> bool:
    """Whether the command printed ``text`` (the console wraps long lines)."""
    return " ".join(text.split()) in " ".join(out.stdout.split())


def any_file(folder: Path, pattern: str):
    """A kill condition: a file matching ``pattern`` exists below ``folder``."""
    return lambda: folder.is_dir() and any(folder.glob(pattern))


@pytest.fixture(scope="module")
def upstream(tmp_path_factory) -> Path:
    """A store with every input of the late stages: captures, scenes, touches, the paired dataset and a model."""
    root = tmp_path_factory.mktemp("upstream")
    run_to_end(root, "pipeline", *TINY, "pipeline.stages=[capture,fit-scene,touch,pair,train]")
    assert (root / "models" / MODEL / "best.ckpt").is_file() and (root / "pairs" / DATASET).is_dir()
    return root


@pytest.fixture(scope="module")
def reference(upstream, tmp_path_factory) -> Path:
    """The whole pipeline run without interruption (its first five stages are the upstream store's)."""
    root = tmp_path_factory.mktemp("reference")
    copy_stages(upstream, root, *UPSTREAM)
    run_to_end(root, *PIPELINE)
    return root


# -- the artifact store's temporary folders ----------------------------------------------------------------
def test_temporary_folders_and_files_of_killed_writers_are_removed_of_live_ones_kept(tmp_path):
    from tnf.artifacts import ArtifactStore, _host, write_json

    store = ArtifactStore(tmp_path)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(dead.stdout)
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        parent = store.path("generated", "run", "builtin")
        folders = {
            "dead": parent / f".ball.{dead_pid}@{_host()}.abc.partial",
            "live": parent / f".ball.{live.pid}@{_host()}.def.partial",
            "elsewhere": parent / f".ball.{dead_pid}@another-host.ghi.partial",
            "other item": parent / f".box.{dead_pid}@{_host()}.jkl.partial",
        }
        for f in folders.values():
            (f / "images").mkdir(parents=True)
        # Writing ball replaces its dead writer's leftovers only; a running job's folder is not touched.
        with store.writing("generated", "run", "builtin", "ball", config={"v": 1}) as tmp:
            assert f".{os.getpid()}@{_host()}." in tmp.name
        assert [k for k, f in folders.items() if f.exists()] == ["live", "elsewhere", "other item"]
        assert store.clean_partials("generated", "run") == 1  # the other item's
        assert [k for k, f in folders.items() if f.exists()] == ["live", "elsewhere"]
        assert store.items("generated") == ["run/builtin/ball"]
        # The same for the temporary files of atomic writes (reports, JSON files).
        files = {
            k: tmp_path / f".results.json.{pid}@{_host()}.xyz.tmp"
            for k, pid in (("dead", dead_pid), ("live", live.pid))
        }
        for f in files.values():
            f.write_text("{half")
        write_json(tmp_path / "results.json", {"n": 1})
        assert [k for k, f in files.items() if f.exists()] == ["live"]
        assert json.loads((tmp_path / "results.json").read_text()) == {"n": 1}
    finally:
        live.kill()
        live.wait()
    assert store.clean_partials("generated") == 1 and folders["elsewhere"].exists()


# -- finetune ----------------------------------------------------------------------------------------------
FINETUNE = (
    "finetune",
    *TINY,
    f"finetune.checkpoint={MODEL}",
    f"data.datasets=[{DATASET}]",
    "finetune.run_name=ft",
    # Epochs of a step or two each: the kill after epoch 1 must leave several to resume, or a fast machine
    # finishes them between two polls of the kill condition.
    "finetune.epochs=6",
    "finetune.decay_epochs=2",
    "finetune.limit_train_batches=2",
    "finetune.freeze=[net_g.encoders.rgb]",
)


@pytest.fixture(scope="module")
def finetune_reference(upstream, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("finetune_ref")
    copy_stages(upstream, root, "pairs", "models")
    run_to_end(root, *FINETUNE)
    return root


def check_finetuned(root: Path, ref: Path) -> dict:
    """The finished fine-tuning run in ``root`` matches the uninterrupted one in ``ref``; returns its last.ckpt."""
    run, ref_run = root / "models" / "ft", ref / "models" / "ft"
    a, b = manifest(run), manifest(ref_run)
    # The same settings: the config names the source checkpoint by its path (which is another store's here) and
    # by its content hash (the same).
    assert a["config"]["source"]["checkpoint_hash"] == b["config"]["source"]["checkpoint_hash"]
    strip = [{**m["config"], "source": {**m["config"]["source"], "checkpoint": None}} for m in (a, b)]
    assert strip[0] == strip[1]
    assert (a["epochs"], a["global_step"]) == (b["epochs"], b["global_step"])
    last, ref_last = ckpt(run / "last.ckpt"), ckpt(ref_run / "last.ckpt")
    assert (last["epoch"], last["global_step"]) == (ref_last["epoch"], ref_last["global_step"])
    # The frozen encoder is still the source model's after the restart.
    source = ckpt(root / "models" / MODEL / "best.ckpt")["state_dict"]
    frozen = [k for k in source if ".encoders.rgb." in k]
    assert frozen and all(torch.equal(last["state_dict"][k], source[k]) for k in frozen)
    assert leftovers(root) == [], leftovers(root)
    return last


def test_finetune_killed_after_an_epoch_resumes_with_optimiser_and_scheduler_state(
    tmp_path, upstream, finetune_reference
):
    root = tmp_path / "data"
    copy_stages(upstream, root, "pairs", "models")
    source = (root / "models" / MODEL / "best.ckpt").read_bytes()
    run = root / "models" / "ft"
    assert kill_when(root, FINETUNE, ckpt_epoch_at_least(run / "last.ckpt", 1), poll=0.05, pause=True)
    assert not (run / "manifest.json").exists()
    killed = ckpt(run / "last.ckpt")
    grid = run / "grids" / "epoch_000.png"  # written once: a resumed run does not train epoch 0 again
    written = grid.stat().st_mtime_ns
    run_to_end(root, *FINETUNE)
    assert grid.stat().st_mtime_ns == written, "the re-run started afresh instead of resuming"
    last = check_finetuned(root, finetune_reference)
    ref_last = ckpt(finetune_reference / "models" / "ft" / "last.ckpt")
    assert last["global_step"] > killed["global_step"]
    # The learning-rate schedule and the optimisers carry on where the killed run stopped: the same state as
    # after an uninterrupted run.
    for sa, sb in zip(last["lr_schedulers"], ref_last["lr_schedulers"], strict=True):
        assert sa["last_epoch"] == sb["last_epoch"] and sa["_last_lr"] == sb["_last_lr"]
    for oa, ob in zip(last["optimizer_states"], ref_last["optimizer_states"], strict=True):
        assert [g["lr"] for g in oa["param_groups"]] == [g["lr"] for g in ob["param_groups"]]
        steps_a = sorted(float(s["step"]) for s in oa["state"].values())
        assert steps_a == sorted(float(s["step"]) for s in ob["state"].values())
    assert (root / "models" / MODEL / "best.ckpt").read_bytes() == source, "the source checkpoint was modified"


@pytest.mark.slow
def test_finetune_killed_before_its_first_checkpoint_starts_afresh(tmp_path, upstream, finetune_reference):
    root = tmp_path / "data"
    copy_stages(upstream, root, "pairs", "models")
    run = root / "models" / "ft"
    # run.json is written when training starts; killed then, the run folder holds no checkpoint yet.
    assert kill_when(root, FINETUNE, (run / "run.json").is_file)
    assert not (run / "last.ckpt").exists() and not (run / "manifest.json").exists()
    run_to_end(root, *FINETUNE)
    last = check_finetuned(root, finetune_reference)
    # Started afresh with the same seed: the very weights of the uninterrupted run.
    ref = ckpt(finetune_reference / "models" / "ft" / "last.ckpt")["state_dict"]
    assert last["state_dict"].keys() == ref.keys()
    for k, v in ref.items():
        assert torch.equal(last["state_dict"][k], v), k


# -- generate ----------------------------------------------------------------------------------------------
def check_generated(root: Path, ref: Path) -> None:
    """Both objects' generated touches equal the uninterrupted run's, image for image."""
    assert [p.name for p in finished_items(root / GENERATED.parent, "builtin")] == ["ball", "box"]
    for obj in ("ball", "box"):
        a, b = root / GENERATED / obj, ref / GENERATED / obj
        assert manifest(a)["config_hash"] == manifest(b)["config_hash"]
        assert manifest(a)["touches"] == manifest(b)["touches"]
        assert tree_bytes(a) == tree_bytes(b), f"{obj}: images differ from an uninterrupted run"
    assert leftovers(root) == [], leftovers(root)


def test_generate_killed_after_the_first_object_resumes(tmp_path, upstream, reference):
    root = tmp_path / "data"
    copy_stages(upstream, root, *UPSTREAM)
    assert kill_when(root, GENERATE, (root / GENERATED / "ball" / "manifest.json").is_file)
    done = manifest_stamps(root, "generated")
    assert [m.parent.name for m in done] == ["ball"]
    out = run_to_end(root, *GENERATE)
    assert said(out, f"{MODEL}/builtin/ball is up to date")
    assert_not_rewritten(done)
    check_generated(root, reference)


@pytest.mark.slow
def test_generate_killed_while_writing_an_object(tmp_path, upstream, reference):
    root = tmp_path / "data"
    copy_stages(upstream, root, *UPSTREAM)
    # Killed after a first batch of the first object: its temporary folder holds some of its images.
    assert kill_when(root, GENERATE, any_file(root / GENERATED, ".ball.*.partial/images/00001.png"))
    assert finished_items(root, "generated") == [] and len(leftovers(root / "generated")) == 1
    run_to_end(root, *GENERATE)
    check_generated(root, reference)


# -- evaluate ----------------------------------------------------------------------------------------------
def evaluate_inputs(root: Path, upstream: Path, reference: Path) -> None:
    copy_stages(upstream, root, "touch", "pairs", "models")
    copy_stages(reference, root, "generated")


def report_files(root: Path) -> dict[str, bytes]:
    """The report's files, without the line that says when it was written and the wall times (the pipeline's
    timings files, the report's section of them and the evaluation's times in each run's results)."""
    files = {k: v for k, v in tree_bytes(root / REPORT).items() if not k.startswith("timings/")}
    for k in [k for k in files if k.endswith("results.json")]:
        results = json.loads(files[k])
        results.pop("evaluate_s")
        results.pop("phases_s")
        files[k] = json.dumps(results, sort_keys=True).encode()
    lines, kept, timed = files["report.md"].split(b"\n"), [], False
    for ln in lines:
        if ln.startswith(b"#"):
            timed = ln.startswith(b"### Wall times")
        if not timed and not ln.startswith(b"Written "):
            kept.append(ln)
    files["report.md"] = b"\n".join(kept)
    return files


def results_of(root: Path) -> dict:
    """The run's results without how long its evaluation and its phases took."""
    results = json.loads((root / RESULTS).read_text())
    assert results.pop("evaluate_s") > 0
    assert results.pop("phases_s")["classify.train"] >= 0
    return results


def check_evaluated(root: Path, ref: Path) -> None:
    a, b = results_of(root), results_of(ref)
    assert a == b  # metrics, accuracies, the environment and the config hash
    assert report_files(root) == report_files(ref)
    assert leftovers(root) == [], leftovers(root)


@pytest.mark.slow
def test_evaluate_killed_while_evaluating_recomputes_the_run(tmp_path, upstream, reference):
    root = tmp_path / "data"
    evaluate_inputs(root, upstream, reference)
    # Killed once the job has started (Hydra has written its config): nothing of the run is kept, not even the
    # example figure, which is written with the results.
    assert kill_when(root, EVALUATE, any_file(root / "logs", "**/.hydra/config.yaml"))
    assert not (root / RESULTS.parent).exists() and not (root / REPORT / "report.md").exists()
    run_to_end(root, *EVALUATE)
    check_evaluated(root, reference)


def test_evaluate_killed_after_its_results_keeps_them_and_writes_the_report(tmp_path, upstream, reference):
    root = tmp_path / "data"
    evaluate_inputs(root, upstream, reference)
    assert kill_when(root, EVALUATE, (root / RESULTS).is_file)
    stamp = (root / RESULTS).stat().st_mtime_ns
    out = run_to_end(root, *EVALUATE)
    assert said(out, "results exist with the same settings, skipped")
    assert (root / RESULTS).stat().st_mtime_ns == stamp, "finished results were recomputed"
    check_evaluated(root, reference)


# -- pipeline ----------------------------------------------------------------------------------------------
def check_pipeline(root: Path, ref: Path, exact_from: tuple[str, ...]) -> None:
    """Every stage's items of ``root`` have the reference's config hashes; the contents of the stages in
    ``exact_from`` (and of what depends only on them) are the reference's too."""
    for stage in UPSTREAM + ("generated",):
        mine = {str(p.relative_to(root)): manifest(p)["config"] for p in finished_items(root, stage)}
        theirs = {str(p.relative_to(ref)): manifest(p)["config"] for p in finished_items(ref, stage)}
        if stage == "generated" and "models" not in exact_from:
            # Generated images record the modification time of the checkpoint they come from: another model file.
            for config in (*mine.values(), *theirs.values()):
                config.pop("checkpoint_mtime")
        assert mine == theirs, stage
    for stage in exact_from:
        for item in finished_items(ref, stage):
            same_arrays(item, root / item.relative_to(ref))
            skip = ("manifest.json", "scene.pt", "metrics.json", "preview.png", "hparams.yaml")
            if stage not in ("scenes", "models"):  # trained: the same settings, not the same bytes
                assert tree_bytes(item, skip) == tree_bytes(root / item.relative_to(ref), skip), item
    a, b = results_of(root), results_of(ref)
    assert a["config_hash"] == b["config_hash"]
    if "generated" in exact_from:
        assert a == b
        assert report_files(root) == report_files(ref)
    assert leftovers(root) == [], leftovers(root)


def test_pipeline_killed_in_generate_and_in_evaluate_resumes(tmp_path, upstream, reference):
    root = tmp_path / "data"
    copy_stages(upstream, root, *UPSTREAM)
    before = manifest_stamps(root, *UPSTREAM)
    # 1: killed while generating the first object; 2: killed after generating, in the evaluation.
    assert kill_when(root, PIPELINE, any_file(root / GENERATED, ".ball.*.partial/images/*.png"))
    assert finished_items(root, "generated") == []
    assert kill_when(
        root, PIPELINE, lambda: len([p for p in finished_items(root, "generated") if p.suffix != ".partial"]) == 2
    )
    assert not (root / RESULTS).exists()
    generated = manifest_stamps(root, "generated")
    assert len(generated) == 2
    out = run_to_end(root, *PIPELINE)
    # Finished stages are skipped, not redone.
    assert_not_rewritten(before)
    assert_not_rewritten(generated)
    for line in ("pair: dataset", "is up to date", "trained with the same settings, skipped", "ball is up to date"):
        assert said(out, line), line
    check_pipeline(root, reference, exact_from=UPSTREAM + ("generated",))
    # The report ends with where the run was evaluated and the pipeline's wall times: the stages of the run that
    # wrote it, up to generate, and evaluate's from its results.
    report = (root / REPORT / "report.md").read_text()
    wall = report[report.index("### Wall times") :].split("\n")
    header = next(ln for ln in wall if ln.startswith("| Model |"))
    assert header == "| Model | device | capture | fit-scene | touch | pair | train | generate | evaluate | total |"
    (row,) = [ln for ln in wall if ln.startswith(f"| {MODEL} | cpu |")]
    assert all(float(c) >= 0 for c in row.strip("| ").split(" | ")[2:])
    assert "| T-N seed 0 | " in report[report.index("### Environment") :]


@pytest.mark.slow
def test_pipeline_from_scratch_killed_in_every_stage_resumes(tmp_path, reference):
    root = tmp_path / "data"
    ball = Path("builtin") / "ball"
    kill_points = {
        "capture": (root / "capture" / ball / "manifest.json").is_file,
        "fit-scene": (root / "scenes" / "hashgrid" / ball / "manifest.json").is_file,
        "touch": (root / "touch" / "digit" / ball / "manifest.json").is_file,
        "pair": (root / "pairs" / ".cache" / DATASET / ball / "manifest.json").is_file,
        "train": ckpt_epoch_at_least(root / "models" / MODEL / "last.ckpt", 0),
    }
    stamps: dict = {}
    for stage, ready in kill_points.items():
        train = stage == "train"
        assert kill_when(root, PIPELINE, ready, poll=0.05 if train else 0.002, pause=train), f"finished before {stage}"
        # Whatever had finished before this kill is still the same files after it.
        assert_not_rewritten(stamps)
        stamps = manifest_stamps(root, "capture", "scenes", "touch", "pairs")
        # The pair stage's per-object caches are removed once the dataset is built.
        stamps = {k: v for k, v in stamps.items() if ".cache" not in k.parts}
    grid = root / "models" / MODEL / "grids" / "epoch_000.png"  # written once: a resumed run does not redo epoch 0
    written = grid.stat().st_mtime_ns
    run_to_end(root, *PIPELINE)
    assert_not_rewritten(stamps)
    assert grid.stat().st_mtime_ns == written, "training did not resume"
    # Training was resumed, which draws other random numbers than an uninterrupted run: what comes after it has
    # the same settings but not the same numbers.
    check_pipeline(root, reference, exact_from=("capture", "touch", "pairs"))
    assert np.isfinite(json.loads((root / RESULTS).read_text())["image"]["novel_view"]["T-N"]["ssim"])
