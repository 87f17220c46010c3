"""Faults during training: a NaN/Inf loss, a full disk while writing a checkpoint and a data worker that dies
each end the run with a clear TnfError, and the last good checkpoint stays intact and loadable."""

from __future__ import annotations

import errno
import os

import lightning as L
import pytest
import torch
from torch.utils.data import DataLoader, get_worker_info

from tests.generators.synthetic import TensorPairs, make_pairs
from tnf.errors import NonFiniteLoss, TnfError
from tnf.generators import load_generator
from tnf.generators.system import GeneratorSystem
from tnf.generators.training import fit

N_TRAIN = 4  # pairs per epoch; batches of 2


class FaultyPairs(TensorPairs):
    """Synthetic pairs that go wrong once the first epoch has been served: ``fault`` = "nan", "inf" or "exit"
    (the worker process ends abruptly). Served items are counted in a file so worker processes share the count."""

    def __init__(self, pairs, fault: str, counter: str):
        super().__init__(pairs)
        self.fault, self.counter = fault, counter

    def __getitem__(self, i):
        item = super().__getitem__(i)
        with open(self.counter, "ab+") as f:
            f.write(b".")
            served = f.tell()
        if served > N_TRAIN:  # from the second epoch on
            if self.fault == "exit" and get_worker_info() is not None:
                os._exit(1)
            if self.fault in ("nan", "inf"):
                item = {**item, "rgb": torch.full_like(item["rgb"], float(self.fault))}
        return item


class Data(L.LightningDataModule):
    def __init__(self, fault: str, counter: str, workers: int = 0):
        super().__init__()
        self.train = FaultyPairs(make_pairs(N_TRAIN, 32, 0), fault, counter)
        self.val = TensorPairs(make_pairs(2, 32, 1))
        self.workers = workers

    def train_dataloader(self):
        return DataLoader(self.train, batch_size=2, num_workers=self.workers)

    def val_dataloader(self):
        return DataLoader(self.val, batch_size=2)


def run(tmp_path, data, **kw):
    system = GeneratorSystem(
        {"name": "tn_cgan", "ngf": 8, "ndf": 8, "image_size": 32}, epochs=3, decay_epochs=1, finite_check_every=1
    )
    return fit(
        system,
        data,
        tmp_path / "run",
        config={"test": 1},
        trainer_cfg={"accelerator": "cpu", "devices": 1, "precision": "32-true"},
        progress=False,
        **kw,
    )


def assert_last_good(run_dir, epoch: int = 0):
    """last.ckpt is the checkpoint of ``epoch``, loads as a generator and holds finite weights."""
    ckpt = torch.load(run_dir / "last.ckpt", map_location="cpu", weights_only=False)
    assert ckpt["epoch"] == epoch
    system = load_generator(run_dir / "last.ckpt")
    assert all(torch.isfinite(p).all() for p in system.parameters())
    assert not (run_dir / "manifest.json").exists()  # an unfinished run is not marked done


@pytest.mark.parametrize("fault", ["nan", pytest.param("inf", marks=pytest.mark.slow)])
def test_non_finite_loss_stops_with_last_good_checkpoint(tmp_path, fault):
    with pytest.raises(NonFiniteLoss, match=r"non-finite training loss .* at epoch 1.*the last good checkpoint is"):
        run(tmp_path, Data(fault, str(tmp_path / "count")))
    assert_last_good(tmp_path / "run")


def test_full_disk_while_writing_a_checkpoint(tmp_path, monkeypatch):
    from fsspec.implementations.local import LocalFileOpener

    real_write = LocalFileOpener.write
    run_dir = tmp_path / "run"

    def write(self, data):  # once the first checkpoint exists, the disk is full half-way through a write
        if (run_dir / "last.ckpt").is_file() and len(data) > 1000:
            real_write(self, data[: len(data) // 2])
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_write(self, data)

    monkeypatch.setattr(LocalFileOpener, "write", write)
    with pytest.raises(TnfError, match="I/O error: No space left on device.*the last good checkpoint is") as e:
        run(tmp_path, Data("none", str(tmp_path / "count")))
    assert "\n" not in str(e.value)
    monkeypatch.undo()
    assert_last_good(run_dir)


def test_data_worker_that_dies(tmp_path):
    with pytest.raises(TnfError, match=r"a data loader worker died .*the last good checkpoint is") as e:
        run(tmp_path, Data("exit", str(tmp_path / "count"), workers=1))
    assert "\n" not in str(e.value)
    assert_last_good(tmp_path / "run")
