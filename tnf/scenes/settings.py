"""The settings of fitting a scene (``cfg.fit``), in a module of their own so that the start-up check of a config
(``tnf.stages.settings``) validates them without importing torch or Lightning. ``tnf.scenes.system`` re-exports
:class:`FitSettings`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from tnf.registry import FROM_YAML, at_least, yaml_defaults, yaml_field

# Defaults per scene kind where one value does not suit both (fit settings of null pick these).
KIND_DEFAULTS: dict[str, dict[str, Any]] = {
    "hashgrid": {"steps": 3000, "batch_rays": 4096, "lr": 1e-2},
    "nerf": {"steps": 30000, "batch_rays": 2048, "lr": 5e-4},
}


def _batched(settings: FitSettings) -> bool:
    """Whether ``batch_objects`` is part of the identity: when it fits objects together (above 1)."""
    return settings.batch_objects > 1


def _kernel(settings: FitSettings) -> bool:
    """Whether ``train_kernel`` is part of the identity: when it is on."""
    return settings.train_kernel


@dataclass
@yaml_defaults("fit/default")
class FitSettings:
    """How to fit one scene (the ``fit`` config section)."""

    steps: int | None = FROM_YAML
    """Training steps (ray batches); null: the scene kind's default (hashgrid 3000, nerf 30000)."""
    batch_rays: int | None = FROM_YAML
    """Rays per training batch; null: the scene kind's default (hashgrid 4096, nerf 2048)."""
    lr: float | None = FROM_YAML
    """Adam learning rate at the start; null: the scene kind's default (hashgrid 1e-2, nerf 5e-4)."""
    lr_final_factor: float = FROM_YAML
    """Learning rate at the last step as a fraction of lr (exponential decay)."""
    random_background: bool = FROM_YAML
    """Composite each training ray's RGBA target over a random colour (teaches empty space to be empty)."""
    checkpoint_every: int = yaml_field(identity=False)
    """Steps between resumable checkpoints (0: none). Not part of a scene's identity: a resumed fit ends exactly
    as an uninterrupted one, however often it saved."""
    eval_views: int | None = FROM_YAML
    """Held-out views to evaluate (null: all of transforms_test.json)."""
    preview_views: int = FROM_YAML
    """Held-out views shown in preview.png."""
    chunk: int | None = yaml_field(identity=False)
    """Rays per rendering chunk during evaluation (bounds memory); null: the scene kind's default. Not part of a
    scene's identity: the fitted scene does not depend on it, the held-out renders (metrics, preview) by float
    rounding only (pixels within 1e-6 of each other on the CPU, equal metrics)."""
    log_every: int = yaml_field(identity=False)
    """Steps between loss records in the training log (metrics.json's ``train_log``). Not part of a scene's
    identity: it changes only how densely the log samples the loss, not the fit."""
    carve: bool = FROM_YAML
    """Start the occupancy grid from the visual hull of the training views' alpha masks (skips empty space)."""
    distortion_weight: float = FROM_YAML
    """Weight of the distortion loss (Mip-NeRF 360) that gathers each ray's weights on one surface; scenes
    that report it (hashgrid) only. The colour loss alone leaves the density profile behind an opaque
    surface free, and a spread-out profile biases the expected depth away from the camera
    (docs/decisions/fit_distortion.md)."""
    distortion_start: float = FROM_YAML
    """Fraction of the steps fitted by colour alone before the distortion loss starts: it gathers each ray's
    weights on the surface the colour has formed by then, rather than on a guess of the first steps."""

    batch_objects: int = yaml_field(identity=_batched)
    """Objects fitted together in one process (``tnf.scenes.batched``; hashgrid only): each training step takes
    ``batch_rays`` rays of each of them through one forward, backward and optimiser step, which keeps a GPU
    busy where one object's small steps leave it idle. 1: each object alone (``tnf.scenes.fit.fit_scene``).
    Part of a scene's identity when above 1: a batched fit equals the separate one only up to float
    rounding (batched matrix products), so its scenes are not the separately fitted ones bit for bit."""

    train_kernel: bool = yaml_field(identity=_kernel)
    """Train a hash grid's encoding and its table gradient by Warp kernels
    (``tnf.scenes.hash_kernel.hash_encode_trainable``) in place of PyTorch's ``[P, L, 8]`` tensors; hashgrid only.
    Faster (0.80x of the training time of 27 batched objects on an H100, 0.83x of one on 2 CPU cores) and equal
    up to float rounding (atomic adds in another order), so part of a scene's identity when on."""

    workers: int = yaml_field(identity=False)
    """Processes that fit the objects, each its share as the job ``shard=i shards=workers`` of a sweep over shards
    would (``tnf.stages.local_workers``), with ``cores / workers`` threads each; 1: this process alone. Warp runs a
    CPU kernel on one thread, so on a CPU of 2 cores 2 workers fit the quick start's 6 hash grids in 0.73x of one
    process's time. Not part of a scene's identity: each object is fitted with the same settings; with
    ``batch_objects`` above 1 the groups are each worker's objects, so their rays are drawn otherwise than in one
    group of all (as in a sweep over shards)."""

    def validate(self) -> None:
        at_least(self, 1, "batch_objects", "workers", "steps", "batch_rays", "log_every")
        at_least(self, 0, "checkpoint_every", "distortion_weight")
        if self.lr is not None and self.lr <= 0:
            raise ValueError(f"lr must be > 0, got {self.lr}")
        if not 0 <= self.distortion_start < 1:
            raise ValueError(f"distortion_start must be in [0, 1), got {self.distortion_start}")
        if not 0 < self.lr_final_factor <= 1:
            raise ValueError(f"lr_final_factor must be in (0, 1], got {self.lr_final_factor}")

    def resolved(self, kind: str) -> FitSettings:
        """A copy with null fields replaced by the scene kind's defaults."""
        d = KIND_DEFAULTS.get(kind, KIND_DEFAULTS["hashgrid"])
        out = FitSettings(**self.__dict__)
        for k, v in d.items():
            if getattr(out, k) is None:
                setattr(out, k, v)
        return out
