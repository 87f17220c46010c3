"""`tnf train trainer=ddp` on two CPU processes (gloo): the run folder is written once and complete, each
process trains on its own half of the pairs, a step of two processes equals one process's step on both halves
as one batch, a DDP run resumes from its last checkpoint, and DDP works under
a Hydra multirun sweep."""

import csv
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from tests.generators.synthetic import make_pairs
from tests.generators.test_stages import model_of, write_pairs
from tnf.generators import load_generator

DDP = ["trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2"]
TINY = ["debug=tiny", "progress=false", "data.batch_size=4", *DDP]


def tnf(*args, root):
    env = {**os.environ, "TNF_DATA": str(root), "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-m", "tnf.cli", *args], capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    return out


def epoch_rows(run_dir, column, name="metrics.csv"):
    with open(run_dir / name) as f:
        return [r for r in csv.DictReader(f) if r.get(column)]


def test_ddp_train_writes_one_complete_loadable_run_with_sharded_epochs(data_root):
    # 12 pairs: 8 train, 4 val; two processes of batch 4 -> one step of 4 pairs each per epoch.
    write_pairs(data_root / "pairs" / "digit-hashgrid", n=12)
    tnf("train", *TINY, root=data_root)
    run_dir = data_root / "models" / model_of("train", *TINY)
    for f in ("last.ckpt", "best.ckpt", "metrics.csv", "manifest.json", "grids/epoch_000.png", "grids/epoch_001.png"):
        assert (run_dir / f).is_file(), f
    # Written by process 0 alone: no second metrics file, no temporary or partial files anywhere.
    assert sorted(p.name for p in run_dir.iterdir()) == [
        ".lock",  # process 0's, held while it trains (artifacts.exclusive)
        "best.ckpt",
        "grids",
        "hparams.yaml",
        "last.ckpt",
        "manifest.json",
        "metrics.csv",
        "run.json",
    ]
    assert sorted(p.name for p in (run_dir / "grids").iterdir()) == ["epoch_000.png", "epoch_001.png"]
    assert not [p for p in (data_root / "models").rglob("*") if p.name.startswith(".") and p.name != ".lock"]
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert manifest["world_size"] == 2 and manifest["epochs"] == 2
    # Manual optimisation without the adversarial term (the default): one generator step per batch, one batch per
    # process and epoch.
    assert manifest["global_step"] == 2
    assert 0 < manifest["best_val_l1"] <= 2 and 0 < manifest["last"]["val_ssim"] <= 1
    # Each epoch the two processes together trained on all 8 training pairs, process 0 on half of them.
    rows = epoch_rows(run_dir, "train/samples")
    assert [int(r["epoch"]) for r in rows] == [0, 1]
    assert all(float(r["train/samples"]) == 8 and float(r["train/rank_samples"]) == 4 for r in rows)
    system = load_generator(run_dir / "best.ckpt")
    assert system.generate(make_pairs(2, 128)).shape == (2, 3, 128, 128)
    ckpt = torch.load(run_dir / "last.ckpt", weights_only=True)
    assert ckpt["epoch"] == 1 and ckpt["global_step"] == 2 and ckpt["optimizer_states"]


def test_ddp_step_equals_one_process_step_on_the_whole_batch(data_root):
    # Two processes of batch 4 average their gradients: one step must move the weights as one process does with
    # the same 8 pairs as a batch of 8 (results/generators/ddp/ shows the same over 12 epochs of training).
    # Instance norm (batch norm's statistics would differ per shard); no dropout, adversarial term or
    # augmentation in tn_cgan's defaults, so nothing random is left but the order of the pairs.
    write_pairs(data_root / "pairs" / "digit-hashgrid", n=12)
    one = ["debug=tiny", "progress=false", "generator.norm=instance", "train.epochs=1", "train.decay_epochs=0"]
    tnf("train", *one, "data.batch_size=8", "train.run_name=one", root=data_root)
    tnf("train", *one, *DDP, "data.batch_size=4", "train.run_name=ddp", root=data_root)
    tnf("train", *one, "data.batch_size=4", "train.limit_train_batches=1", "train.run_name=half", root=data_root)

    def weights(name):
        ckpt = torch.load(data_root / "models" / name / "last.ckpt", weights_only=True)
        assert ckpt["global_step"] == 1
        return {k: v for k, v in ckpt["state_dict"].items() if k.startswith("generator.") and v.is_floating_point()}

    w_one, w_ddp, w_half = weights("one"), weights("ddp"), weights("half")
    assert w_one.keys() == w_ddp.keys() and len(w_one) > 10

    def moved_apart(w):  # the share of weights that differ from the one-process step's
        return float(torch.cat([((w_one[k] - w[k]).abs() > 1e-6).flatten() for k in w_one]).float().mean())

    # Adam's first step moves each weight by the learning rate in the direction of its gradient's sign, so
    # the same step agrees exactly but where a gradient is zero up to rounding (a bias before instance norm):
    # 0.05 % of the weights here. A step on 4 of the 8 pairs (one process's without the average): 14 %.
    assert moved_apart(w_ddp) < 0.002 and moved_apart(w_half) > 0.05, (moved_apart(w_ddp), moved_apart(w_half))


@pytest.mark.slow
def test_killed_ddp_run_resumes_from_its_last_checkpoint(data_root):
    write_pairs(data_root / "pairs" / "digit-hashgrid", n=12)
    args = ["-m", "tnf.cli", "train", *TINY, "train.epochs=3", "train.decay_epochs=0"]
    env = {**os.environ, "TNF_DATA": str(data_root), "OMP_NUM_THREADS": "1"}
    run_dir = data_root / "models" / model_of(*args[2:])
    # Kill the whole process group (the command and its DDP processes) once the first epoch's checkpoint is
    # there, as a lost node would.
    proc = subprocess.Popen(
        [sys.executable, *args], env=env, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    deadline = time.monotonic() + 600
    while not (run_dir / "last.ckpt").is_file() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (run_dir / "manifest.json").exists(), "the run finished before it could be killed"
    done = torch.load(run_dir / "last.ckpt", weights_only=True)["epoch"]  # the last epoch that was saved
    assert done < 2
    killed = [r for r in epoch_rows(run_dir, "epoch") if int(r["epoch"]) <= done]
    tnf("train", *TINY, "train.epochs=3", "train.decay_epochs=0", root=data_root)
    manifest = json.loads((run_dir / "manifest.json").read_text())
    # One generator step per batch (no adversarial term, the default), one batch per process and epoch.
    assert manifest["epochs"] == 3 and manifest["global_step"] == 3 and manifest["world_size"] == 2
    # metrics.csv holds the run's whole history once: the killed run's rows of the epochs its checkpoint holds
    # (last.ckpt is in place only once they are written), then the epochs the rerun trained, each on all 8
    # pairs split between the processes.
    assert epoch_rows(run_dir, "epoch")[: len(killed)] == killed
    assert [int(r["epoch"]) for r in epoch_rows(run_dir, "val_l1")] == [0, 1, 2]
    assert [int(r["step"]) for r in epoch_rows(run_dir, "train/loss_g_step")] == [0, 1, 2]
    rows = epoch_rows(run_dir, "train/samples")
    assert [int(r["epoch"]) for r in rows] == [0, 1, 2]
    assert all(float(r["train/samples"]) == 8 and float(r["train/rank_samples"]) == 4 for r in rows)
    assert sorted(p.name for p in run_dir.glob("*.csv")) == ["metrics.csv"]
    assert torch.load(run_dir / "last.ckpt", weights_only=True)["epoch"] == 2


@pytest.mark.slow
@pytest.mark.parametrize("launcher", ["basic", "joblib"])
def test_ddp_under_a_multirun_sweep(data_root, launcher):
    # joblib: the sweep's jobs run in parallel worker processes, each of which spawns its DDP processes.
    extra = []
    if launcher == "joblib":
        pytest.importorskip("hydra_plugins.hydra_joblib_launcher", reason="needs hydra-joblib-launcher")
        extra = ["hydra.launcher.n_jobs=2"]
    write_pairs(data_root / "pairs" / "digit-hashgrid", n=12)
    sweep = ["train.epochs=1", "train.decay_epochs=0", "seed=0,1", "train.run_name=s${seed}"]
    tnf("train", "-m", f"hydra/launcher={launcher}", *extra, *TINY, *sweep, root=data_root)
    for name in ("s0", "s1"):
        manifest = json.loads((data_root / "models" / name / "manifest.json").read_text())
        assert manifest["world_size"] == 2 and manifest["epochs"] == 1 and manifest["config"]["seed"] == int(name[1])
        assert load_generator(data_root / "models" / name / "last.ckpt").generator_name == "tn_cgan"


@pytest.mark.slow
def test_ddp_with_processes_started_by_torchrun(data_root):
    # torchrun starts both processes, each running the whole stage: Lightning starts none, process 0 writes.
    write_pairs(data_root / "pairs" / "digit-hashgrid", n=12)
    env = {**os.environ, "TNF_DATA": str(data_root), "OMP_NUM_THREADS": "1"}
    cmd = ["-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", "-m", "tnf.cli", "train", *TINY]
    out = subprocess.run([sys.executable, *cmd], capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    run_dir = data_root / "models" / model_of("train", *TINY)
    assert out.stdout.count(f"{run_dir.name}: 2 epochs") == 1  # the summary, from process 0 alone
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert manifest["world_size"] == 2 and manifest["epochs"] == 2 and manifest["global_step"] == 2
    rows = epoch_rows(run_dir, "train/samples")
    assert all(float(r["train/samples"]) == 8 and float(r["train/rank_samples"]) == 4 for r in rows)
    assert not [p for p in (data_root / "models").rglob("*") if p.name.startswith(".") and p.name != ".lock"]


@pytest.mark.slow
def test_diverged_ddp_run_stops_every_process_with_a_one_line_error(data_root):
    folder = data_root / "pairs" / "digit-hashgrid"
    write_pairs(folder, n=12)
    depth = np.load(folder / "depth.npy", mmap_mode="r+")
    depth[0, 60:68, 60:68] = np.nan  # a corrupt pair of the training split, in one process's shard
    depth.flush()
    env = {**os.environ, "TNF_DATA": str(data_root), "OMP_NUM_THREADS": "1"}
    out = subprocess.run(
        [sys.executable, "-m", "tnf.cli", "train", *TINY], capture_output=True, text=True, env=env, timeout=600
    )
    assert out.returncode == 1
    assert "error: non-finite training loss" in out.stderr and "in DDP process" in out.stderr
    assert "Traceback" not in out.stderr
    assert not (data_root / "models" / model_of("train", *TINY) / "manifest.json").exists()


@pytest.mark.parametrize(
    ("spec", "static"),
    [({"name": "tn_cgan"}, True), ({"name": "tn_cgan", "lambda_gan": 1.0}, False), ({"name": "lee"}, False)],
)
def test_ddp_uses_a_static_graph_only_where_every_step_is_one_backward(spec, static):
    # A regression (tn_cgan without its adversarial term) back-propagates through the same parameters every
    # step; a GAN alternates between networks, which a static graph refuses at its second step.
    from tnf.generators.training import ddp_strategy, static_graph_synced
    from tnf.registry import GENERATORS

    fixed = GENERATORS.build(spec).fixed_graph()
    assert fixed is static
    kwargs = ddp_strategy("ddp", fixed_graph=fixed)._ddp_kwargs
    # Where Lightning would not average the first step's gradients under a static graph, none is used.
    static = static and static_graph_synced()
    assert kwargs == ({"static_graph": True} if static else {"find_unused_parameters": True})


def test_ddp_trains_a_gan_whose_steps_back_propagate_through_different_networks(data_root):
    # With the adversarial term each step updates the discriminator, then the generator: DDP must find the
    # parameters each backward leaves without gradients (no static graph).
    write_pairs(data_root / "pairs" / "digit-hashgrid", n=12)
    tnf("train", *TINY, "generator.lambda_gan=1.0", "train.run_name=gan", root=data_root)
    manifest = json.loads((data_root / "models" / "gan" / "manifest.json").read_text())
    # Two optimiser steps (discriminator, generator) per batch, one batch per process and epoch, two epochs.
    assert manifest["world_size"] == 2 and manifest["global_step"] == 4
    rows = epoch_rows(data_root / "models" / "gan", "train/loss_d_epoch")
    assert len(rows) == 2 and all(float(r["train/loss_d_epoch"]) > 0 for r in rows)
