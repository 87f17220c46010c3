"""Paired visuo-tactile datasets: preprocessing, splits, the on-disk format, datasets and the DataModule.

``PairDataModule`` (it imports Lightning) and ``render_pairs_for_touches`` are imported on first use.
"""

from __future__ import annotations

from typing import Any

from tnf.data.augment import AUGMENTATIONS, augment_batch, mirror_batch, sensor_mirror
from tnf.data.dataset import (
    MixedPairDataset,
    PairDataset,
    collate_pairs,
    to_float_batch,
    training_order,
)
from tnf.data.preprocess import SIZE, crop_for_sensor, preprocess_rgbd, resize_uint8
from tnf.data.splits import SPLITS, assign_splits, choose_novel_objects
from tnf.data.store import PairArrays, PairWriter, dataset_name, open_pairs, write_manifest

__all__ = [
    "AUGMENTATIONS",
    "SIZE",
    "SPLITS",
    "MixedPairDataset",
    "PairArrays",
    "PairDataModule",
    "PairDataset",
    "PairWriter",
    "assign_splits",
    "augment_batch",
    "choose_novel_objects",
    "collate_pairs",
    "datamodule_from_config",
    "dataset_name",
    "crop_for_sensor",
    "mirror_batch",
    "open_pairs",
    "preprocess_rgbd",
    "render_pairs_for_touches",
    "resize_uint8",
    "sensor_mirror",
    "to_float_batch",
    "training_order",
    "write_manifest",
]

_LAZY = {
    "PairDataModule": "tnf.data.datamodule",
    "datamodule_from_config": "tnf.data.datamodule",
    "render_pairs_for_touches": "tnf.data.render",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'tnf.data' has no attribute {name!r}")
