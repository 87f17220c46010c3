"""Stages killed part-way (SIGKILL) and run again: same result as an uninterrupted run, finished items are not
redone, and a half-written item is never taken for a finished one."""

from __future__ import annotations

import json
import time

import pytest
import torch

from tests.reliability.helpers import QUIET, finished_items, kill_when, partials, run_to_end, same_arrays, tree_bytes


def manifest(folder):
    return json.loads((folder / "manifest.json").read_text())


def check_resumed(root, ref_root, stage, items, done_before):
    """After the re-run: every item finished with the reference's config hash and content; items finished
    before the kill kept their manifests (not recomputed); no temporary folder is left."""
    assert partials(root / stage) == []
    for item in items:
        a, b = root / stage / item, ref_root / stage / item
        assert manifest(a)["config_hash"] == manifest(b)["config_hash"]
        same_arrays(a, b)
        assert (
            tree_bytes(a, skip=("manifest.json", "scene.pt", "metrics.json")).keys()
            == tree_bytes(b, skip=("manifest.json", "scene.pt", "metrics.json")).keys()
        )
    for path, (mtime, created) in done_before.items():
        assert path.stat().st_mtime_ns == mtime, f"{path} was rewritten"
        assert json.loads(path.read_text())["created"] == created


def snapshot(root, stage):
    """Manifests of the finished items of ``stage``: path -> (mtime, created)."""
    out = {}
    for folder in finished_items(root, stage):
        if any(part.startswith(".") for part in folder.relative_to(root / stage).parts):
            continue
        m = folder / "manifest.json"
        out[m] = (m.stat().st_mtime_ns, json.loads(m.read_text())["created"])
    return out


CAPTURE = ("capture", *QUIET, "object_names=[ball,box]", "capture.num_views=6", "capture.num_test_views=1")


@pytest.fixture(scope="module")
def capture_reference(tmp_path_factory):
    root = tmp_path_factory.mktemp("ref")
    run_to_end(root, *CAPTURE)
    return root


def test_capture_killed_after_first_object_resumes(tmp_path, capture_reference):
    root = tmp_path / "data"
    first = root / "capture" / "builtin" / "ball" / "manifest.json"
    assert kill_when(root, CAPTURE, first.is_file), "capture finished before it could be killed"
    # What the kill left: the finished item, possibly the next one's temporary folder, never its manifest.
    assert [p.name for p in finished_items(root, "capture")] == ["ball"]
    assert all(not (p / "manifest.json").exists() or p.name.startswith(".") for p in partials(root))
    before = snapshot(root, "capture")
    run_to_end(root, *CAPTURE)
    check_resumed(root, capture_reference, "capture", ["builtin/ball", "builtin/box"], before)
    # Rendering is deterministic: the images are the reference's, byte for byte.
    assert tree_bytes(root / "capture/builtin/box") == tree_bytes(capture_reference / "capture/builtin/box")


def test_capture_killed_while_writing_an_item(tmp_path, capture_reference):
    # An item's images are written within milliseconds: poll fast, and try again with a fresh store when the
    # capture slipped past the kill point.
    for attempt in range(5):
        root = tmp_path / f"data{attempt}"
        part = root / "capture" / "builtin"
        if kill_when(root, CAPTURE, lambda part=part: any(part.glob(".*.partial/images/*.png")), poll=0.001):
            break
    else:
        pytest.fail("capture finished five times before it could be killed while writing an item")
    assert finished_items(root, "capture") == [] or [p.name for p in finished_items(root, "capture")] == ["ball"]
    run_to_end(root, *CAPTURE)
    check_resumed(root, capture_reference, "capture", ["builtin/ball", "builtin/box"], {})


TOUCH = ("touch", *QUIET, "object_names=[ball,box]", "touch.n_touches=4", "touch.n_val=1", "touch.n_novel_view=1")


@pytest.mark.slow
def test_touch_killed_after_first_object_resumes(tmp_path):
    ref = tmp_path / "ref"
    run_to_end(ref, *TOUCH)
    root = tmp_path / "data"
    first = root / "touch" / "digit" / "builtin" / "ball" / "manifest.json"
    assert kill_when(root, TOUCH, first.is_file)
    before = snapshot(root, "touch")
    run_to_end(root, *TOUCH)
    check_resumed(root, ref, "touch", ["digit/builtin/ball", "digit/builtin/box"], before)
    for obj in ("ball", "box"):
        a, b = manifest(root / "touch/digit/builtin" / obj), manifest(ref / "touch/digit/builtin" / obj)
        assert a["touches"] == b["touches"]
        assert tree_bytes(root / "touch/digit/builtin" / obj) == tree_bytes(ref / "touch/digit/builtin" / obj)


PAIR = ("pair", *QUIET, "pair.scene_source=mesh", "pair.render_batch=2", "pair.keep_cache=true")


@pytest.mark.slow
def test_pair_killed_after_first_cache_resumes(tmp_path):
    from tests.data.pair_inputs import make_inputs

    ref, root = tmp_path / "ref", tmp_path / "data"
    for r in (ref, root):
        make_inputs(r, touches=6, scenes=False)
    run_to_end(ref, *PAIR)
    first = root / "pairs" / ".cache" / "digit-mesh" / "builtin" / "ball" / "manifest.json"
    assert kill_when(root, PAIR, first.is_file)
    assert not (root / "pairs" / "digit-mesh" / "manifest.json").exists()
    before = snapshot(root, "pairs")
    before = {k: v for k, v in before.items() if "ball" in str(k)}
    before[first] = (first.stat().st_mtime_ns, manifest(first.parent)["created"])
    run_to_end(root, *PAIR)
    assert first.stat().st_mtime_ns == before[first][0], "the finished render cache was recomputed"
    same_arrays(root / "pairs" / "digit-mesh", ref / "pairs" / "digit-mesh", rounding=True)
    assert manifest(root / "pairs/digit-mesh")["config_hash"] == manifest(ref / "pairs/digit-mesh")["config_hash"]
    assert partials(root) == []


TRAIN = ("train", *QUIET, "data.batch_size=2", "train.epochs=4", "train.decay_epochs=2", "train.limit_train_batches=2")


def _ckpt(path):
    return torch.load(path, map_location="cpu", weights_only=False)


@pytest.mark.slow
@pytest.mark.parametrize("augment", ["[]", "[mirror,jitter]"])
def test_train_killed_resumes_from_last_checkpoint_with_optimiser_state(tmp_path, augment):
    from tests.generators.test_stages import model_of, write_pairs

    ref, root = tmp_path / "ref", tmp_path / "data"
    for r in (ref, root):
        write_pairs(r / "pairs" / "digit-hashgrid", n=9)
    train = (*TRAIN, f"data.augment={augment}")
    run_to_end(ref, *train)
    run_dir = root / "models" / model_of(*train)
    last = run_dir / "last.ckpt"

    def after_second_epoch():
        if not last.is_file():
            return False
        try:
            return _ckpt(last)["epoch"] >= 1
        except Exception:  # being written
            return False

    assert kill_when(root, train, after_second_epoch, poll=0.05, pause=True)
    assert not (run_dir / "manifest.json").exists()
    killed = _ckpt(last)
    grid = run_dir / "grids" / "epoch_000.png"  # written once: a resumed run does not train epoch 0 again
    written = grid.stat().st_mtime_ns
    run_to_end(root, *train)
    assert grid.stat().st_mtime_ns == written, "the re-run started afresh instead of resuming"
    a, b = _ckpt(run_dir / "last.ckpt"), _ckpt(ref / "models" / run_dir.name / "last.ckpt")
    progress = [(c["epoch"], c["global_step"]) for c in (killed, a, b)]
    assert progress[1] == progress[2] and progress[1][1] > progress[0][1], progress
    for sa, sb in zip(a["lr_schedulers"], b["lr_schedulers"]):
        assert sa["last_epoch"] == sb["last_epoch"] and sa["_last_lr"] == sb["_last_lr"]
    for oa, ob in zip(a["optimizer_states"], b["optimizer_states"]):
        assert [g["lr"] for g in oa["param_groups"]] == [g["lr"] for g in ob["param_groups"]]
        steps_a = sorted(float(s["step"]) for s in oa["state"].values())
        steps_b = sorted(float(s["step"]) for s in ob["state"].values())
        assert steps_a == steps_b, "optimiser step counters differ from an uninterrupted run"

    # The metrics history is an uninterrupted run's: every epoch's validation row, once, with the same values.
    def val_rows(folder):
        import csv

        rows = [r for r in csv.DictReader(open(folder / "metrics.csv")) if r.get("val_l1")]
        return [(int(r["epoch"]), round(float(r["val_l1"]), 5)) for r in rows]

    assert val_rows(run_dir) == val_rows(ref / "models" / run_dir.name)
    assert [e for e, _ in val_rows(run_dir)] == [0, 1, 2, 3]
    # The weights are an uninterrupted run's, whatever the augmentation (its draws are not in the checkpoint).
    for k, wa in a["state_dict"].items():
        assert torch.allclose(wa.float(), b["state_dict"][k].float(), rtol=1e-4, atol=1e-5), (
            k,
            (wa.float() - b["state_dict"][k].float()).abs().max(),
        )
    assert manifest(run_dir)["config_hash"] == manifest(ref / "models" / run_dir.name)["config_hash"]


@pytest.mark.slow
def test_fit_scene_killed_resumes(tmp_path, capture_reference):
    import shutil

    root = tmp_path / "data"
    shutil.copytree(capture_reference / "capture", root / "capture")
    fit = ("fit-scene", *QUIET, "object=ball", "fit.steps=120", "fit.checkpoint_every=40")
    t0 = time.monotonic()
    resume = root / "scenes" / ".resume"
    killed = kill_when(root, fit, lambda: any(resume.rglob("*.pt")) if resume.is_dir() else False)
    assert killed, f"fit-scene finished in {time.monotonic() - t0:.0f} s before writing a resume checkpoint"
    assert finished_items(root, "scenes") == []
    run_to_end(root, *fit)
    out = root / "scenes" / "hashgrid" / "builtin" / "ball"
    assert (out / "scene.pt").is_file() and partials(root / "scenes") == []
    # The resumed fit ends bit for bit where an uninterrupted one does.
    ref = tmp_path / "ref"
    shutil.copytree(capture_reference / "capture", ref / "capture")
    run_to_end(ref, *fit)
    a = torch.load(out / "scene.pt", weights_only=True)["state"]
    b = torch.load(ref / "scenes" / "hashgrid" / "builtin" / "ball" / "scene.pt", weights_only=True)["state"]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    ma, mb = (
        json.loads((d / "scenes" / "hashgrid" / "builtin" / "ball" / "metrics.json").read_text()) for d in (root, ref)
    )
    assert ma["train_log"] == mb["train_log"] and ma["psnr"] == mb["psnr"]


def test_capture_interrupted_by_ctrl_c_is_one_line_and_resumes(tmp_path):
    import os
    import signal
    import subprocess

    from tests.reliability.helpers import tnf_cmd, tnf_env
    from tnf.cli import INTERRUPTED

    # Started with Ctrl-C's default action even where the test runner ignores it (a background job).
    for attempt in range(5):
        root = tmp_path / f"data{attempt}"
        first = root / "capture" / "builtin" / "ball" / "manifest.json"
        p = subprocess.Popen(
            tnf_cmd(*CAPTURE),
            env=tnf_env(root),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )
        while p.poll() is None:
            os.killpg(p.pid, signal.SIGSTOP)
            if first.is_file():
                os.killpg(p.pid, signal.SIGINT)
                os.killpg(p.pid, signal.SIGCONT)
                break
            os.killpg(p.pid, signal.SIGCONT)
            time.sleep(0.002)
        err = p.communicate(timeout=300)[1]
        if p.returncode != 0:
            break
    else:
        pytest.fail("capture finished five times before it could be interrupted")
    assert p.returncode == 130, err[-3000:]
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1] == f"error: {INTERRUPTED}"
    run_to_end(root, *CAPTURE)
    assert [p.name for p in finished_items(root, "capture")] == ["ball", "box"]
