"""`tnf train` killed with SIGKILL once it has a checkpoint, then run again: it resumes, and its metrics.csv holds
the run's whole history, every step's rows once and in order, as an uninterrupted run's does."""

import csv
import os
import signal
import subprocess
import sys

import torch

from tests.generators.test_stages import write_pairs

EPOCHS = 5
# Two batches of 4 pairs per epoch (8 training pairs), one validation batch: 10 steps in all.
TRAIN = ["debug=tiny", "progress=false", "data.batch_size=4", f"train.epochs={EPOCHS}", "train.decay_epochs=1"]


def command(root, run_name):
    env = {**os.environ, "TNF_DATA": str(root), "OMP_NUM_THREADS": "1"}
    return [sys.executable, "-m", "tnf.cli", "train", *TRAIN, f"train.run_name={run_name}"], env


def run_to_end(root, run_name):
    cmd, env = command(root, run_name)
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]


def rows(run_dir):
    with open(run_dir / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def shape(table):
    """Each row as (epoch, step, the columns it holds values of)."""
    return [
        (int(r["epoch"]), int(r["step"]), tuple(k for k, v in r.items() if v and k not in ("epoch", "step")))
        for r in table
    ]


def test_killed_run_resumes_with_its_whole_metrics_history(data_root):
    write_pairs(data_root / "pairs" / "digit-hashgrid", n=12)
    run_to_end(data_root, "whole")
    whole = shape(rows(data_root / "models" / "whole"))

    run_dir = data_root / "models" / "killed"
    cmd, env = command(data_root, "killed")
    proc = subprocess.Popen(cmd, env=env, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        # Poll the run folder until the first checkpoint is in place, then kill the command at once.
        while not (run_dir / "last.ckpt").is_file() and proc.poll() is None:
            try:
                proc.wait(timeout=0.02)
            except subprocess.TimeoutExpired:
                pass
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    assert proc.returncode == -signal.SIGKILL, "the run ended before it could be killed"
    assert not (run_dir / "manifest.json").exists()
    done = torch.load(run_dir / "last.ckpt", weights_only=True)["epoch"] + 1  # epochs the checkpoint holds
    assert done < EPOCHS
    killed = rows(run_dir)
    before = [r for r in killed if int(r["epoch"]) < done]

    run_to_end(data_root, "killed")
    final = rows(run_dir)
    assert torch.load(run_dir / "last.ckpt", weights_only=True)["epoch"] == EPOCHS - 1
    # The same rows as the uninterrupted run: each step's training losses once, steps 0 to 9 in order, and each
    # epoch's validation and training metrics once, after its last step.
    assert shape(final) == whole
    steps = [int(r["step"]) for r in final if r["train/loss_g_step"]]
    assert steps == list(range(2 * EPOCHS))
    assert [int(r["epoch"]) for r in final if r["val_l1"]] == list(range(EPOCHS))
    assert [int(r["epoch"]) for r in final if r["lr/g"]] == list(range(EPOCHS))
    # The epochs the checkpoint held are the killed run's own rows, as it logged them.
    assert final[: len(before)] == before and len(before) >= 4
    assert sorted(p.name for p in run_dir.glob("*.csv")) == ["metrics.csv"]
    assert not list(run_dir.glob("*.pending"))
