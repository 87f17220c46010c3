"""The LightningDataModule over one or several paired datasets."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch.utils.data import DataLoader, DistributedSampler

from tnf.artifacts import MANIFEST, data_root
from tnf.data.augment import augment_batch, check_augment, mirror_augment
from tnf.data.dataset import (
    Batch,
    MixedPairDataset,
    PairDataset,
    check_subsample,
    collate_pairs,
    to_float_batch,
)
from tnf.data.settings import DataSettings
from tnf.data.store import open_pairs
from tnf.errors import TnfError

TEST_SPLITS = ("novel_view", "novel_object")


def resolve_dataset(folder: str | os.PathLike[str], root: str | os.PathLike[str] | None = None) -> Path:
    """A dataset folder given as a path, or as a name under ``<data_root>/pairs/``."""
    p = Path(folder).expanduser()
    if (p / MANIFEST).is_file():
        return p
    named = data_root(root) / "pairs" / str(folder)
    if (named / MANIFEST).is_file():
        return named
    raise TnfError(f"no paired dataset at {p} nor {named}; build one with `tnf pair`")


class PairDataModule(L.LightningDataModule):
    """Batches of pairs for training a generator: dicts of float32 tensors in [-1, 1] (``rgb`` [B, 3, 128, 128],
    ``depth`` [B, 1, 128, 128], ``background`` [B, 3, 128, 128], ``tactile`` [B, 3, 128, 128]) and
    ``object_id`` [B] long, indexing ``object_names`` (the union of the datasets' objects, in order).

    Args:
        folders: dataset folders (or names under ``<data_root>/pairs``); several are mixed into one.
        batch_size: pairs per batch.
        num_workers: DataLoader worker processes (0 loads in the main process).
        per_object: at most this many touches per object and dataset; None keeps all.
        extra_touches: with ``per_object``, this many more touches per dataset, drawn from all objects' others.
        augment: augmentations of the training batches, from ``tnf.data.AUGMENTATIONS`` (see ``augment_batch``);
            ``mirror`` needs every dataset to come from sensors with the same mirror symmetry, and is left out
            (with a warning) where they have none (``tnf.data.dataset.mirror_augment``).
        pin_memory: page-locked batches for faster copies to a GPU.
        seed: seed of the subsample and the training order.
        train_splits, val_splits: splits served by ``train_dataloader`` / ``val_dataloader``.
        drop_last: drop the last, incomplete training batch.
        data_root: where dataset names are looked up (default the configured artifact root).
        convert_on_device: the loaders serve compact batches (uint8 images, float16 depth; see
            ``PairDataset``), and ``on_after_batch_transfer`` converts them to the float form (and augments)
            on the training device; 4x less data to load, pin and copy. Off: the loaders serve float batches.
    """

    def __init__(
        self,
        folders: Sequence[str | os.PathLike[str]],
        batch_size: int = 64,
        num_workers: int = 0,
        per_object: int | None = None,
        augment: Sequence[str] = (),
        pin_memory: bool = False,
        seed: int = 0,
        train_splits: Sequence[str] = ("train",),
        val_splits: Sequence[str] = ("val",),
        drop_last: bool = False,
        data_root: str | os.PathLike[str] | None = None,
        convert_on_device: bool = False,
        extra_touches: int = 0,
    ):
        super().__init__()
        if isinstance(folders, (str, os.PathLike)):
            folders = [folders]
        if not folders:
            raise TnfError("PairDataModule needs at least one dataset folder")
        if batch_size < 1:
            raise TnfError(f"batch_size must be >= 1, got {batch_size}")
        check_subsample(per_object, extra_touches)
        self.folders = [resolve_dataset(f, data_root) for f in folders]
        self.batch_size = batch_size
        self.num_workers = num_workers
        self.per_object = per_object
        self.extra_touches = extra_touches
        self.augment = check_augment(augment)
        self.pin_memory = pin_memory
        self.seed = seed
        self.train_splits = tuple(train_splits)
        self.val_splits = tuple(val_splits)
        self.drop_last = drop_last
        self.convert_on_device = convert_on_device
        # Every array checked (readable, shapes, row counts against the manifest) before training writes anything.
        manifests = [open_pairs(f).manifest for f in self.folders]
        names: list[str] = []
        for m in manifests:
            for n in m["objects"]:
                if n not in names:
                    names.append(n)
        self.object_names = names
        self.augment, self.mirror = mirror_augment(self.augment, list(zip(manifests, self.folders)))
        self._augmented = (-1, 0)  # (epoch, batches augmented in it): what seeds the next batch's augmentation

    def dataset(self, splits: Sequence[str], augment: Sequence[str] = ()) -> PairDataset | MixedPairDataset:
        """The pairs of ``splits`` over all folders (one dataset, or a mix)."""
        parts = [
            PairDataset(
                f,
                splits,
                self.per_object,
                self.seed,
                object_names=self.object_names,
                augment=augment,
                compact=self.convert_on_device,
                extra_touches=self.extra_touches,
            )
            for f in self.folders
        ]
        return parts[0] if len(parts) == 1 else MixedPairDataset(parts)

    def _loader(self, splits: Sequence[str], train: bool) -> DataLoader:
        ds = self.dataset(splits)  # training batches are augmented after the transfer (on_after_batch_transfer)
        if len(ds) == 0:
            raise TnfError(f"no pairs in split(s) {', '.join(splits)} of {', '.join(map(str, self.folders))}")
        sampler = self._distributed_sampler(ds, shuffle=train)
        if sampler is None and train:
            # One process's "shard" is the whole dataset, shuffled from (seed, epoch) alone (Lightning calls
            # set_epoch): a run resumed at an epoch sees the order an uninterrupted run saw there.
            sampler = DistributedSampler(ds, num_replicas=1, rank=0, shuffle=True, seed=self.seed, drop_last=False)
        return DataLoader(
            ds,
            batch_size=self.batch_size,
            shuffle=None if sampler is not None else False,
            sampler=sampler,
            drop_last=train and self.drop_last,
            num_workers=self.num_workers,
            pin_memory=self.pin_memory,
            persistent_workers=self.num_workers > 0,
            collate_fn=collate_pairs,
        )

    def _distributed_sampler(self, ds: Any, shuffle: bool) -> DistributedSampler | None:
        """Under a distributed trainer (DDP), a sampler that gives this process its own 1/world-size shard of
        ``ds``, reshuffled every epoch (Lightning calls ``set_epoch``) from ``seed``; None otherwise.

        (Lightning would insert one itself, but seeded from ``PL_GLOBAL_SEED`` rather than this seed.)
        """
        trainer = self.trainer
        kwargs = trainer.distributed_sampler_kwargs if trainer is not None else None
        if not kwargs:
            return None
        # drop_last=False: the last shard is padded with repeated pairs so every process runs as many steps.
        return DistributedSampler(ds, shuffle=shuffle, seed=self.seed, drop_last=False, **kwargs)

    def on_after_batch_transfer(self, batch: Batch, dataloader_idx: int) -> Batch:
        if self.convert_on_device:
            batch = to_float_batch(batch)
        trainer = getattr(self, "trainer", None)
        if self.augment and trainer is not None and trainer.training:
            augment_batch(batch, self.augment, self.mirror, generator=self._augment_generator(trainer))
        return batch

    def _augment_generator(self, trainer: Any) -> torch.Generator:
        """The random draws of the next training batch's augmentation, from ``seed``, the epoch, the batch's
        number in it and the process's rank alone: a run resumed from a checkpoint draws what an uninterrupted
        run drew (the global random state is not part of the checkpoint)."""
        epoch, count = self._augmented
        epoch_now = int(trainer.current_epoch)
        count = count if epoch == epoch_now else 0
        self._augmented = (epoch_now, count + 1)
        rank = int(getattr(trainer, "global_rank", 0))
        key = ((self.seed * 1_000_003 + epoch_now) * 1_000_003 + count) * 64 + rank
        return torch.Generator().manual_seed(key % (2**63 - 1))

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.train_splits, train=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.val_splits, train=False)

    def test_dataloader(self, split: str | None = None) -> DataLoader | list[DataLoader]:
        """One split's loader (``novel_view``, ``novel_object``, ...), or both test splits' when None."""
        if split is None:
            return [self._loader((s,), train=False) for s in TEST_SPLITS]
        return self._loader((split,), train=False)


def datamodule_from_config(
    data: DataSettings, seed: int, data_root: Any, datasets: Sequence[str] | None = None
) -> PairDataModule:
    """A ``PairDataModule`` from the ``data`` section (every setting of it), the seed and the data root;
    ``datasets`` replaces ``data.datasets``."""
    settings = {f.name: getattr(data, f.name) for f in dataclasses.fields(data) if f.name != "datasets"}
    return PairDataModule(
        list(datasets) if datasets is not None else [str(d) for d in data.datasets or []],
        seed=seed,
        data_root=data_root,
        **settings,
    )
