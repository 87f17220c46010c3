"""Settings of the data stages, as validated dataclasses: ``PairSettings`` (the ``pair`` section, read by
``tnf.data.pairing``) and ``DataSettings`` (the ``data`` section, read by ``tnf.data.datamodule``).

Kept apart from the modules that use them, which import torch, so that every stage checks every section before
any work without importing it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from tnf.data.splits import SPLITS
from tnf.registry import FROM_YAML, SettingError, at_least, yaml_defaults, yaml_field

AUGMENTATIONS = ("mirror", "shift", "jitter")
"""What ``data.augment`` may list: ``mirror``, the sensor's own mirror symmetry (``Sensor.mirror_channels``:
pairs flipped left-right with the tactile and background channels reordered, as real as the simulated ones);
``shift``, half the pairs moved sideways by up to the image's half-size, the press's change from the background
with them (a contact anywhere on the gel, where the simulator pressed at its centre);
``jitter``, +-10 % brightness and contrast of the RGB image (``tnf.data.augment.augment_batch``)."""


@dataclass
@yaml_defaults("pair/default")
class PairSettings:
    """The ``pair`` section: pairing each touch with RGB-D rendered at its pose, and the dataset's splits."""

    name: str | None = FROM_YAML
    """Dataset name under ``<data_root>/pairs/``; null: ``<sensor>-<scene>`` (fitted) or ``<sensor>-mesh``."""
    scene_source: Literal["fitted", "mesh"] = FROM_YAML
    """Where the RGB-D comes from: ``fitted`` (the object's fitted scene) or ``mesh`` (its ground-truth mesh)."""
    crop_distance: str = FROM_YAML
    """Where the gel footprint that sizes each crop is measured: ``contact`` (per touch, at first contact) or
    ``fixed`` (one crop for all, at ``footprint_distance``)."""
    crop_px: int | None = FROM_YAML
    """Side of a fixed square centre crop, pixels of the capture camera; null: sized by ``crop_distance``."""
    crop_extent: str = FROM_YAML
    """What a per-view crop shows: ``footprint`` (``crop_margin`` times the gel's larger side) or ``sensor``
    (exactly the gel patch the tactile image shows)."""
    crop_margin: float = FROM_YAML
    """Factor applied to the gel footprint (1: exactly the gel's larger side; ``crop_extent=footprint``)."""
    footprint_distance: float | None = FROM_YAML
    """Reference distance from the camera to the surface, metres; null: the median of the touches' contacts."""
    depth_norm: str = FROM_YAML
    """Depth normalisation: ``contact`` (first contact at 0.5), ``center`` (the centre pixel at 0.5) or
    ``minmax`` (over the crop)."""
    depth_window: float = FROM_YAML
    """Depth range, metres, mapped onto [0, 1] by ``depth_norm=contact`` and ``center``."""
    novel_objects: list[str] | None = FROM_YAML
    """Held-out objects of the novel_object split; null: ``num_novel_objects`` drawn with the seed."""
    num_novel_objects: int = FROM_YAML
    """Held-out objects drawn when ``novel_objects`` is null."""
    render_px: int | None = FROM_YAML
    """Pixels per side rendered for each touch's crop; null: ``max(128, crop)``."""
    render_batch: int = yaml_field(identity=False)
    """Touches rendered per batch (bounds renderer memory)."""
    render_chunk: int | None = yaml_field(identity=False)
    """Rays per chunk inside the scene renderer; null: the scene's default."""
    previews: int = yaml_field(identity=False)
    """Pairs written as PNG strips to ``previews/``."""
    prior: bool = FROM_YAML
    """Also store each pair's prior (``prior.npy``): the simulator's image of its depth crop."""
    points: bool = FROM_YAML
    """Also store each RGB-D pixel's surface point in the object's frame (``points.npy``, metres)."""
    force: bool = FROM_YAML
    """Also store each pair's touch force (``force.npy``, newtons)."""
    keep_cache: bool = yaml_field(identity=False)
    """Keep the per-object render caches after assembling."""

    def validate(self) -> None:
        at_least(self, 0, "num_novel_objects", "previews")
        at_least(self, 1, "render_batch", "render_chunk")  # crop_px and render_px: checked by Framing


@dataclass
@yaml_defaults("data/default")
class DataSettings:
    """The ``data`` section: which paired datasets a generator trains on and how their batches are served."""

    datasets: list[str | None] | None = FROM_YAML
    """Datasets to serve: names under ``<data_root>/pairs/`` or folder paths, several mixed; null (or a null
    entry): the dataset ``tnf pair`` builds with the current settings."""
    batch_size: int = FROM_YAML
    """Pairs per batch."""
    num_workers: int = yaml_field(identity=False)
    """DataLoader worker processes (0: load in the main process)."""
    per_object: int | None = FROM_YAML
    """At most this many touches per object and dataset (all frames of each kept touch); null keeps all."""
    extra_touches: int = FROM_YAML
    """With ``per_object``: this many more touches per dataset, drawn from all objects' other touches."""
    augment: list[str] = FROM_YAML
    """Augmentations of the training batches, any of ``AUGMENTATIONS``."""
    pin_memory: bool = yaml_field(identity=False)
    """Page-locked batches for faster host-to-GPU copies."""
    train_splits: list[str] = FROM_YAML
    """Splits served by the training loader (of ``SPLITS``)."""
    val_splits: list[str] = FROM_YAML
    """Splits served by the validation loader (of ``SPLITS``)."""
    drop_last: bool = FROM_YAML
    """Drop the last incomplete training batch."""
    convert_on_device: bool = FROM_YAML
    """Serve compact batches (uint8 images, float16 depth) and convert them to float on the training device
    (where training batches are augmented, so a part of what a run draws)."""

    def validate(self) -> None:
        at_least(self, 1, "batch_size", "per_object")
        at_least(self, 0, "num_workers", "extra_touches")
        if self.extra_touches and self.per_object is None:
            raise SettingError("extra_touches", "adds to data.per_object's touches: give data.per_object too")
        unknown = [a for a in self.augment if a not in AUGMENTATIONS]
        if unknown:
            raise SettingError("augment", f"unknown augmentation {unknown[0]!r}; known: {', '.join(AUGMENTATIONS)}")
        for name in ("train_splits", "val_splits"):
            wrong = [s for s in getattr(self, name) if s not in SPLITS]
            if wrong:
                raise SettingError(name, f"unknown split {wrong[0]!r}; splits: {', '.join(SPLITS)}")
