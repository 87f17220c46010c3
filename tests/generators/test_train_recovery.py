"""`tnf train` recovering from what stops or spoils a run: a Ctrl+C during training is tnf's interruption (one
line, exit 130) and the same command resumes; a finished run whose best.ckpt is gone is trained again."""

from __future__ import annotations

import csv
import json
import signal

import pytest
import torch
from lightning.pytorch.callbacks import Callback

from tests.data.pair_inputs import SphereScene
from tests.generators.test_stages import TINY, write_pairs
from tnf.artifacts import write_json
from tnf.cli import INTERRUPTED
from tnf.scenes import save_scene


def tnf(capsys, *args):
    """``tnf ARGS`` in this process: (exit code, stdout, the ``error:`` lines of stderr)."""
    from tnf.cli import main

    capsys.readouterr()
    rc = main(list(args))
    out, err = capsys.readouterr()
    return rc, out, [ln for ln in err.splitlines() if ln.startswith("error:")]


class Probe(Callback):
    """Records each training batch as (epoch, batch index); sends this process a SIGINT (a Ctrl+C) at the start
    of batch ``stop_at``."""

    def __init__(self):
        self.batches = []
        self.stop_at = None
        self.sig = signal.SIGINT

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.batches.append((trainer.current_epoch, batch_idx))
        if self.batches[-1] == self.stop_at:
            signal.raise_signal(self.sig)


@pytest.fixture
def probe(monkeypatch):
    """A ``Probe`` joined to the callbacks of every training run; SIGINT's handler is put back afterwards."""
    from tnf.generators import callbacks

    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    p, build = Probe(), callbacks.build_callbacks
    monkeypatch.setattr(callbacks, "build_callbacks", lambda cfg=None: [*build(cfg), p])
    sigterm = signal.getsignal(signal.SIGTERM)
    yield p
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, sigterm)


# Two training batches of 4 pairs per epoch (8 training pairs of 12), two epochs.
TRAIN = ("train", *TINY, "train.epochs=2", "train.decay_epochs=1", "train.run_name=run")


def test_ctrl_c_during_training_is_an_interruption_and_the_same_command_resumes(data_root, probe, capsys):
    write_pairs(data_root / "pairs" / "digit-hashgrid", n=12)
    run_dir = data_root / "models" / "run"
    probe.stop_at = (1, 1)  # last.ckpt of epoch 0 is in place
    rc, out, errors = tnf(capsys, *TRAIN)
    assert (rc, errors) == (130, [f"error: {INTERRUPTED}"])
    assert "Detected KeyboardInterrupt" not in out
    # Ctrl+C works again (Lightning ignores SIGINT once it has caught one).
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert not (run_dir / "manifest.json").exists()
    assert torch.load(run_dir / "last.ckpt", weights_only=True)["epoch"] == 0

    probe.batches, probe.stop_at = [], None
    rc, _, errors = tnf(capsys, *TRAIN)
    assert (rc, errors) == (0, [])
    assert probe.batches == [(1, 0), (1, 1)]  # resumed after epoch 0
    assert json.loads((run_dir / "manifest.json").read_text())["epochs"] == 2
    with open(run_dir / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    # Each step's training losses once and each epoch's validation once, as in an uninterrupted run.
    assert [int(r["step"]) for r in rows if r["train/loss_g_step"]] == [0, 1, 2, 3]
    assert [int(r["epoch"]) for r in rows if r["val_l1"]] == [0, 1]


def test_sigterm_during_training_is_an_error_not_success_and_the_same_command_resumes(data_root, probe, capsys):
    """A scheduler stops a job with SIGTERM: Lightning ends the fit with exit status 0, which tnf turns into its
    one-line error (exit 1), so that the job is not taken for finished."""
    write_pairs(data_root / "pairs" / "digit-hashgrid", n=12)
    run_dir = data_root / "models" / "run"
    probe.stop_at, probe.sig = (1, 1), signal.SIGTERM
    rc, _, errors = tnf(capsys, *TRAIN)
    assert rc == 1 and len(errors) == 1
    assert errors[0].startswith("error: training stopped by SIGTERM; the last good checkpoint is ")
    assert not (run_dir / "manifest.json").exists()
    probe.batches, probe.stop_at = [], None
    rc, _, errors = tnf(capsys, *TRAIN)
    assert (rc, errors) == (0, []) and (run_dir / "manifest.json").is_file()
    assert probe.batches[0][0] == 1  # resumed after epoch 0


def test_a_finished_run_without_its_best_checkpoint_is_trained_again(data_root, probe, capsys):
    write_pairs(data_root / "pairs" / "digit-hashgrid", n=6)
    # The object's fitted scene and the capture camera generate needs (as in test_generate's trained_model).
    save_scene(SphereScene(SphereScene.Config(radius=0.04)), data_root / "scenes" / "hashgrid" / "builtin" / "ball")
    write_json(
        data_root / "capture" / "builtin" / "ball" / "transforms.json",
        {"fl_x": 200.0, "fl_y": 200.0, "w": 128, "h": 128},
    )
    short = ("train.epochs=1", "train.decay_epochs=0")
    train = ("train", *TINY, *short)
    generate = ("generate", *TINY, *short, "object=ball", "device=cpu", "generate.crop_px=48", "generate.n_poses=2")
    assert tnf(capsys, *train)[0] == 0
    (run_dir,) = (data_root / "models").iterdir()
    (run_dir / "best.ckpt").unlink()

    rc, _, errors = tnf(capsys, *generate)
    assert rc == 1 and len(errors) == 1
    assert "checkpoint not found" in errors[0] and "train.force=true" in errors[0]

    probe.batches = []
    rc, out, errors = tnf(capsys, *train)
    assert (rc, errors) == (0, [])
    assert f"{run_dir.name}: finished, but its best.ckpt is missing; training it again" in out
    assert "skipped" not in out
    assert probe.batches == [(0, 0)]  # trained again from the start
    assert (run_dir / "best.ckpt").is_file() and (run_dir / "manifest.json").is_file()
    rc, _, errors = tnf(capsys, *generate)
    assert (rc, errors) == (0, [])
    assert len(list((data_root / "generated" / run_dir.name / "builtin" / "ball").glob("**/*.png"))) >= 2
    # Finished and whole again: skipped.
    probe.batches = []
    rc, out, _ = tnf(capsys, *train)
    assert rc == 0 and "skipped" in out and probe.batches == []
