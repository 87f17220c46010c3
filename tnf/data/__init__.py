"""Paired visuo-tactile datasets: preprocessing, splits, the on-disk format, datasets and the DataModule.

Every name is imported on first use (most import torch, ``PairDataModule`` Lightning), so that the stage
settings of ``tnf.data.settings`` are checked without them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from tnf.data.augment import AUGMENTATIONS, augment_batch, mirror_batch, sensor_mirror
    from tnf.data.datamodule import PairDataModule, datamodule_from_config
    from tnf.data.dataset import MixedPairDataset, PairDataset, collate_pairs, to_float_batch, training_order
    from tnf.data.preprocess import SIZE, crop_for_sensor, preprocess_rgbd, resize_uint8
    from tnf.data.render import render_pairs_for_touches
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
    **dict.fromkeys(("AUGMENTATIONS", "augment_batch", "mirror_batch", "sensor_mirror"), "tnf.data.augment"),
    **dict.fromkeys(("PairDataModule", "datamodule_from_config"), "tnf.data.datamodule"),
    **dict.fromkeys(
        ("MixedPairDataset", "PairDataset", "collate_pairs", "to_float_batch", "training_order"), "tnf.data.dataset"
    ),
    **dict.fromkeys(("SIZE", "crop_for_sensor", "preprocess_rgbd", "resize_uint8"), "tnf.data.preprocess"),
    "render_pairs_for_touches": "tnf.data.render",
    **dict.fromkeys(("SPLITS", "assign_splits", "choose_novel_objects"), "tnf.data.splits"),
    **dict.fromkeys(("PairArrays", "PairWriter", "dataset_name", "open_pairs", "write_manifest"), "tnf.data.store"),
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'tnf.data' has no attribute {name!r}")
