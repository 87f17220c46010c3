"""Fine-tuning a generator on real presses: the press pairs, the library call (from a checkpoint, from scratch,
with simulated pairs mixed in) and `tnf finetune finetune.presses=...` end to end, with its one-line errors."""

import json

import numpy as np
import pytest
import torch

from tests.real.tiny_generator import TINY, train_tiny_generator
from tnf.data import open_pairs, resize_uint8
from tnf.errors import TnfError
from tnf.real import report
from tnf.real.finetune import finetune_on_presses, write_press_pairs
from tnf.real.generated import generate_presses
from tnf.real.presses import at_sensor_size
from tnf.registry import SENSORS

TINY_GENERATOR = {"name": "tn_cgan", "ngf": 8, "ndf": 8}


@pytest.fixture(scope="module")
def sensor():
    return SENSORS.build({"name": "gelsight_mini", "width": 80, "height": 60})


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return tmp_path_factory.mktemp("ft") / "tnf-data"


@pytest.fixture(scope="module")
def checkpoint(root):
    return train_tiny_generator(root)


def weights(path):
    state = torch.load(path, weights_only=True)["state_dict"]
    return {k: v for k, v in state.items() if k.startswith("generator.")}


def test_press_pairs_hold_the_real_frames_and_backgrounds(taxim_presses, sensor, tmp_path):
    info = write_press_pairs(taxim_presses, sensor, [0, 1, 2], tmp_path / "pairs", val=[5])
    a = open_pairs(tmp_path / "pairs")
    assert info["counts"]["train"] == 3 and info["counts"]["val"] == 1 and len(a) == 4
    sp = at_sensor_size(taxim_presses, sensor, [0, 1, 2, 5])
    assert np.array_equal(a.tactile, resize_uint8(sp.frames))
    assert np.array_equal(a.backgrounds[0], resize_uint8(sp.background))
    assert list(a.touch_index) == [0, 1, 2, 5] and a.manifest["presses"]["train"] == [0, 1, 2]
    assert a.manifest["preprocess"]["depth_norm"] == "contact"  # framed as a paired dataset of touches
    # Without validation presses the training presses are validated on.
    info = write_press_pairs(taxim_presses, sensor, [0, 1], tmp_path / "self")
    assert info["counts"]["train"] == 2 and info["counts"]["val"] == 2
    with pytest.raises(TnfError, match="press 1 is both a training and a validation press"):
        write_press_pairs(taxim_presses, sensor, [0, 1], tmp_path / "bad", val=[1])


def test_finetune_on_presses_from_a_checkpoint_and_from_scratch(checkpoint, taxim_presses, sensor, tmp_path):
    source = checkpoint.read_bytes()
    out = finetune_on_presses(checkpoint, taxim_presses, sensor, [0, 1, 2, 3], tmp_path / "ft", steps=2, val=[4])
    assert out == tmp_path / "ft" / "last.ckpt" and out.is_file() and (tmp_path / "ft" / "best.ckpt").is_file()
    assert checkpoint.read_bytes() == source  # the source checkpoint is untouched
    before, after = weights(checkpoint), weights(out)
    assert before.keys() == after.keys()
    assert any(not torch.equal(before[k], after[k]) for k in before)
    manifest = json.loads((tmp_path / "ft" / "manifest.json").read_text())
    assert manifest["train_pairs"] == 4 and manifest["global_step"] > 0
    assert manifest["source"]["checkpoint"] == str(checkpoint.resolve())
    assert manifest["presses"]["train"] == [0, 1, 2, 3] and manifest["presses"]["val"] == [4]
    sp = at_sensor_size(taxim_presses, sensor, [20, 21])
    images = generate_presses(out, sensor, sp, taxim_presses.radius_mm * 1e-3)
    assert images.shape == (2, 60, 80, 3) and np.isfinite(images).all()

    scratch = finetune_on_presses(
        None, taxim_presses, sensor, [0, 1, 2, 3], tmp_path / "scratch", steps=2, generator=TINY_GENERATOR
    )
    assert scratch.is_file()
    state = weights(scratch)
    assert any(not torch.equal(state[k], before[k]) for k in before if k in state)


def test_finetune_on_presses_with_simulated_pairs(checkpoint, root, taxim_presses, sensor, tmp_path):
    out = finetune_on_presses(
        checkpoint, taxim_presses, sensor, [0, 1], tmp_path / "plus", steps=1, batch_size=4,
        sim=root / "pairs" / "synthetic", sim_pairs=3,
    )  # fmt: skip
    manifest = json.loads((tmp_path / "plus" / "manifest.json").read_text())
    assert out.is_file() and manifest["train_pairs"] == 5
    a = open_pairs(tmp_path / "plus" / "pairs")
    assert a.objects == ["indenter", "ball", "box"] and len(a.backgrounds) == 2
    with pytest.raises(TnfError, match="steps must be"):
        finetune_on_presses(checkpoint, taxim_presses, sensor, [0], tmp_path / "zero", steps=0)


def test_finetune_validates_every_n_epochs(checkpoint, taxim_presses, sensor, tmp_path):
    """Four one-batch epochs validated every second one: validation rows and grids after epochs 1 and 3 only."""
    import csv

    run = tmp_path / "sparse"
    finetune_on_presses(checkpoint, taxim_presses, sensor, [0, 1], run, steps=4, val_every_n_epochs=2)
    with open(run / "metrics.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert sorted({int(r["epoch"]) for r in rows if r.get("val_l1")}) == [1, 3]
    assert sorted(p.name for p in (run / "grids").glob("*.png")) == ["epoch_001.png", "epoch_003.png"]
    assert json.loads((run / "manifest.json").read_text())["config"]["val_every_n_epochs"] == 2


def test_finetune_stage_on_a_press_folder(checkpoint, root, taxim_presses, capsys):
    from tnf.stages import finetune
    from tnf.testing import compose

    real = [
        *TINY, f"data_root={root}", f"finetune.presses={taxim_presses.folder}", f"finetune.checkpoint={checkpoint}",
        "finetune.press_train=[0,1,2]", "finetune.press_test=[20,21]", "finetune.run_name=real",
    ]  # fmt: skip
    out = finetune.run(compose("finetune", real))
    run_dir = root / "models" / "real"
    record = json.loads((run_dir / "realism.json").read_text())
    assert record["test"] == [20, 21] and out["press_realism"] == record["mean"][run_dir.name]
    assert set(out["press_realism"]) == set(report.ALL_METRICS)
    assert (run_dir / "realism.md").is_file() and (run_dir / "realism.png").is_file()
    assert "crop SSIM" in capsys.readouterr().out
    pairs = open_pairs(root / "pairs" / f"presses-{taxim_presses.folder.name}-gelsight_mini")
    assert pairs.manifest["counts"]["train"] == 3 and list(pairs.touch_index) == [0, 1, 2, 0, 1, 2]
    # The run's key holds the press pairs' content (the dataset it trained on), not the simulated dataset's.
    keyed = json.loads((run_dir / "manifest.json").read_text())["config"]["datasets"]
    assert keyed == {pairs.folder.name: pairs.manifest["config_hash"]}
    # The same settings again: skipped; from scratch: its own run.
    assert finetune.run(compose("finetune", real))["skipped"]
    # A run whose scoring never finished (stopped, or failed): the same settings again score it, without training.
    (run_dir / "realism.json").unlink()
    again = finetune.run(compose("finetune", real))
    assert again["skipped"] and again["press_realism"] == pytest.approx(record["mean"][run_dir.name])
    assert (run_dir / "realism.json").is_file()
    scratch = finetune.run(compose("finetune", [*real[:-1], "finetune.checkpoint=null", "finetune.press_test=[]"]))
    assert scratch["run_name"].startswith(f"tn_cgan+ft-presses-{taxim_presses.folder.name}-gelsight_mini-seed0-")


@pytest.mark.parametrize(
    ("setting", "line"),
    [
        (["finetune.press_test=[2,20]"], "finetune: press 2 is both a training and a test press"),
        (["finetune.presses=/no/such/folder"], "no presses.json in /no/such/folder: not a press folder"),
        (["data.per_object=5"], "data.per_object subsamples the touches of each object"),
        (["finetune.press_reference=flat"], "finetune.press_reference must be one of gel, contact"),
        (["finetune.press_test=[40]"], "finetune.press_test: press 40 does not exist: "),
        (["finetune.press_depth_scale=10"], "finetune.press_depth_scale=10: press 0: depth 3.6"),
    ],
)
def test_finetune_stage_refuses_bad_press_settings_in_one_line(root, taxim_presses, capsys, setting, line):
    from tnf.cli import main

    args = [*TINY, f"data_root={root}", f"finetune.presses={taxim_presses.folder}", "finetune.press_train=[0,1,2]"]
    capsys.readouterr()
    assert main(["finetune", *args, *setting]) == 1
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and line in err[0], err


@pytest.mark.parametrize("variant", ["real", "real_fs", "real_plus"])
def test_the_real_transfers_start_from_the_model_the_pipeline_names(variant):
    """transfer=real and real_plus fine-tune the T-N model `tnf pipeline experiment=sim_gelsight_mini` trains with
    the same seed; real_fs trains that network from scratch; all train on the calibration's training presses."""
    from tnf.generators.names import HASH_CHARS
    from tnf.stages.settings import check_settings
    from tnf.stages.train import model_run
    from tnf.testing import compose, hydra_job

    with hydra_job("pipeline", ["experiment=sim_gelsight_mini", "seed=1"]) as cfg:
        mini = model_run(cfg)
    cfg = compose("finetune", ["experiment=sim_gelsight_mini", f"transfer={variant}", "seed=1"])
    check_settings(cfg)
    # The checkpoint names the model by its run family: its run id without the settings hash.
    family = None if variant == "real_fs" else mini[: -HASH_CHARS - 1]
    assert cfg.finetune.checkpoint == family
    assert cfg.finetune.presses == "taxim:gelsight_mini" and cfg.data.per_object is None
    assert list(cfg.finetune.press_train) == list(cfg.calibrate.train) == list(range(16))
    assert list(cfg.finetune.press_test) == list(range(16, 24))
    assert cfg.finetune.press_sim_pairs == (16 if variant == "real_plus" else 0)
