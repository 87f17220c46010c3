"""Lightning callbacks of a model run (``tnf train``, ``tnf finetune``), built from the ``callbacks`` config group.

Each callback holds one idea and works on a ``GeneratorSystem``:

- ``WeightAverage``: moves the generator's weight average (``generator_ema``, kept with ``ema_decay``) towards its
  weights after every training step.
- ``FiniteCheck``: stops training on a NaN or Inf training loss.
- ``DiscriminatorWatch``: logs whether the discriminator tells real from generated images apart almost always.
- ``ImageGrids``: writes an image grid of validation pairs each epoch and shows it in TensorBoard or W&B.
- ``EpochTimes``: logs where each epoch's wall time went: training steps, validation, and the rest.

``conf/callbacks/default.yaml`` lists them by name with their settings (:func:`build_callbacks`);
``callbacks.NAME=null`` on the command line leaves one out. Every run also has ``LatestCheckpoint``
(``last.ckpt``), which ``tnf.generators.training`` adds with ``best.ckpt``'s ``ModelCheckpoint``.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lightning.pytorch.callbacks import Callback, ModelCheckpoint

from tnf.env import conf_dir
from tnf.errors import NonFiniteLoss, TnfError
from tnf.registry import FROM_YAML, from_dict, yaml_defaults

log = logging.getLogger(__name__)

#: Suffix of a checkpoint written but not yet in place (``LatestCheckpoint``).
PENDING = ".pending"

#: The option of the ``callbacks`` group that holds each callback's default settings.
DEFAULTS = "callbacks/default"


class WeightAverage(Callback):
    """Moves ``GeneratorSystem.generator_ema`` towards the generator's weights after every training step.

    The decay per step is the system's ``ema_decay`` (a hyper-parameter, since it decides what its checkpoints
    hold); the first steps decay less, ``min(ema_decay, (1 + n) / (10 + n))`` after n updates, so that the
    average soon leaves its starting weights. The update count is the system's ``ema_updates`` buffer, saved in
    checkpoints, so a resumed run goes on with it. A system without an average is left alone.
    """

    @dataclasses.dataclass
    @yaml_defaults(DEFAULTS, node="weight_average")
    class Config:
        """No settings: the decay is the system's ``ema_decay`` (``train.ema_decay``, ``finetune.ema_decay``)."""

    def __init__(self, config: Config | None = None):
        self.config = config or self.Config()
        self._n: int | None = None  # ema_updates as a Python int, read once (reading it waits for the GPU)

    def on_train_start(self, trainer: Any, pl_module: Any) -> None:
        self._n = None  # read the count a resumed run restored at the first update

    def on_train_batch_end(self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, batch_idx: int) -> None:
        self.update(pl_module)

    @torch.no_grad()
    def update(self, system: Any) -> None:
        """One update of ``system.generator_ema``: parameters and float buffers move towards the generator's, other
        buffers are copied."""
        avg_module = system.generator_ema
        if avg_module is None:
            return
        if self._n is None:
            self._n = int(system.ema_updates)
        decay = min(float(system.hparams["ema_decay"]), (1 + self._n) / (10 + self._n))
        avg: list[torch.Tensor] = list(avg_module.parameters())
        cur: list[torch.Tensor] = list(system.generator.parameters())
        torch._foreach_lerp_(avg, cur, 1.0 - decay)
        for a, c in zip(avg_module.buffers(), system.generator.buffers(), strict=True):
            if a.is_floating_point():
                a.lerp_(c, 1.0 - decay)
            else:
                a.copy_(c)
        system.ema_updates.add_(1)
        self._n += 1


class FiniteCheck(Callback):
    """Stops training with ``NonFiniteLoss`` when a training loss is NaN or Inf.

    The losses of every step are checked every ``finite_check_every`` steps (the system's hyper-parameter; each
    check waits for the GPU), before validation and at the end of each epoch, before the checkpoints are
    written: a diverged model never overwrites ``last.ckpt``. In a distributed run every process stops together.
    """

    @dataclasses.dataclass
    @yaml_defaults(DEFAULTS, node="finite_check")
    class Config:
        """No settings: the interval is the system's ``finite_check_every`` (``train.finite_check_every``)."""

    def __init__(self, config: Config | None = None):
        self.config = config or self.Config()
        self._bad: torch.Tensor | None = None  # a bool on the device: a loss since the last check was not finite
        self._last: dict[str, torch.Tensor] = {}

    def on_train_batch_end(self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, batch_idx: int) -> None:
        losses: dict[str, torch.Tensor] = dict(outputs or {})
        self._last = losses
        bad = torch.stack([~torch.isfinite(v.float()).all() for v in losses.values()]).any()
        self._bad = bad if self._bad is None else (self._bad | bad)
        every = int(pl_module.hparams["finite_check_every"])
        if every > 0 and (batch_idx + 1) % every == 0:
            self.check(trainer)

    def on_validation_epoch_start(self, trainer: Any, pl_module: Any) -> None:
        if not trainer.sanity_checking:
            self.check(trainer)

    def on_train_epoch_end(self, trainer: Any, pl_module: Any) -> None:
        self.check(trainer)

    def check(self, trainer: Any) -> None:
        """Raise ``NonFiniteLoss`` if a loss since training started was not finite (in any process)."""
        bad = self._bad is not None and bool(self._bad)
        if trainer.world_size > 1:
            # Every rank stops together (a rank that stopped alone would leave the others waiting).
            bad = trainer.strategy.reduce_boolean_decision(bad, all=False)
        if bad:
            names = [k for k, v in self._last.items() if not torch.isfinite(v.float()).all()]
            raise NonFiniteLoss(
                f"non-finite training loss ({', '.join(names) or 'earlier in the epoch'}) at epoch "
                f"{trainer.current_epoch}, step {trainer.global_step}; training stopped (lower the learning rate, "
                "use precision=32-true, or check the dataset for NaN)"
            )


def discriminator_saturated(d_real: float, d_fake: float, threshold: float) -> bool:
    """Whether mean discriminator outputs on real and generated images (probabilities in [0, 1]) show that it
    tells them apart (almost) always: ``d_real >= threshold`` and ``d_fake <= 1 - threshold``."""
    return d_real >= threshold and d_fake <= 1.0 - threshold


class DiscriminatorWatch(Callback):
    """Watches the adversarial game of generators that report their discriminator's mean outputs on real and
    generated images (``d_real``, ``d_fake`` among their training-step losses).

    Logs ``train/d_saturated`` each epoch: 1 when, over the whole epoch, the discriminator told the two apart
    almost always (:func:`discriminator_saturated`). The epochs where that starts and ends are also logged as
    warnings: while it lasts, the generator's adversarial loss is large and pulls it away from its image losses
    (docs/decisions/train_discriminator_watch.md).
    """

    @dataclasses.dataclass
    @yaml_defaults(DEFAULTS, node="discriminator_watch")
    class Config:
        """Settings of ``DiscriminatorWatch``."""

        threshold: float = FROM_YAML

        def validate(self) -> None:
            if not 0.5 < self.threshold <= 1.0:
                raise ValueError(f"threshold must be in (0.5, 1], got {self.threshold}")

    def __init__(self, config: Config | None = None):
        self.config = config or self.Config()
        self._sum: torch.Tensor | None = None  # this epoch's summed (d_real, d_fake), kept on the device
        self._steps = 0
        self._was_saturated = False

    def on_train_epoch_start(self, trainer: Any, pl_module: Any) -> None:
        self._sum, self._steps = None, 0

    def on_train_batch_end(self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, batch_idx: int) -> None:
        losses = outputs or {}
        if "d_real" in losses and "d_fake" in losses:
            d = torch.stack([losses["d_real"].detach().float(), losses["d_fake"].detach().float()])
            self._sum = d if self._sum is None else self._sum + d
            self._steps += 1

    def on_train_epoch_end(self, trainer: Any, pl_module: Any) -> None:
        if self._sum is None:
            return
        d = self._sum / self._steps
        if trainer.world_size > 1:  # every process runs this hook in the same order
            d = trainer.strategy.reduce(d, reduce_op="mean")
        d_real, d_fake = (float(v) for v in d.tolist())
        saturated = discriminator_saturated(d_real, d_fake, self.config.threshold)
        pl_module.log("train/d_saturated", float(saturated), on_epoch=True, on_step=False)
        if saturated != self._was_saturated and trainer.global_rank == 0:
            self._warn(saturated, trainer.current_epoch, d_real, d_fake, pl_module.hparams["generator"])
        self._was_saturated = saturated

    @staticmethod
    def _warn(saturated: bool, epoch: int, d_real: float, d_fake: float, generator: Mapping[str, Any]) -> None:
        if not saturated:
            log.warning(
                "epoch %d: the discriminator no longer saturates (mean outputs %.3f real, %.3f generated)",
                epoch,
                d_real,
                d_fake,
            )
            return
        hints = ["generator.gan_mode=lsgan"] if generator.get("gan_mode") == "vanilla" else []
        hints += ["generator.lambda_gan=0"] if "lambda_gan" in generator else []
        log.warning(
            "epoch %d: the discriminator tells real from generated images apart almost always (mean outputs %.3f "
            "real, %.3f generated); while it does, its gradient pulls the generator away from the image losses. "
            "If it lasts, try %s.",
            epoch,
            d_real,
            d_fake,
            " or ".join([*hints, "another seed"]),
        )


class ImageGrids(Callback):
    """Each epoch, an image grid of the first ``grid_rows`` validation pairs (the system's hyper-parameter; 0
    draws none): ``<folder>/epoch_XXX.png`` in the run folder (the trainer's ``default_root_dir``) and the image
    ``val/grid`` in TensorBoard or W&B when one logs. Process 0 alone writes; the sanity check writes none.
    Layout: :func:`image_grid`."""

    @dataclasses.dataclass
    @yaml_defaults(DEFAULTS, node="image_grids")
    class Config:
        """Settings of ``ImageGrids``."""

        folder: str = FROM_YAML

    def __init__(self, config: Config | None = None):
        self.config = config or self.Config()
        self._batch: dict[str, torch.Tensor] | None = None  # the grid's pairs so far, on the CPU

    def on_validation_epoch_start(self, trainer: Any, pl_module: Any) -> None:
        self._batch = None

    def on_validation_batch_end(
        self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, batch_idx: int, dataloader_idx: int = 0
    ) -> None:
        rows = int(pl_module.hparams["grid_rows"])
        if rows <= 0 or not outputs or (self._batch is not None and len(self._batch["fake"]) >= rows):
            return
        part = {k: v[:rows].detach().float().cpu() for k, v in batch.items() if v.ndim == 4}
        part["fake"] = outputs["fake"][:rows].detach().float().cpu()
        if self._batch is None:
            self._batch = part
        else:
            need = rows - len(self._batch["fake"])
            self._batch = {k: torch.cat([self._batch[k], part[k][:need]]) for k in self._batch if k in part}

    def on_validation_epoch_end(self, trainer: Any, pl_module: Any) -> None:
        if trainer.sanity_checking or self._batch is None or not trainer.is_global_zero:
            return
        grid = image_grid(self._batch)
        from PIL import Image

        folder = Path(trainer.default_root_dir) / self.config.folder
        folder.mkdir(parents=True, exist_ok=True)
        # The fastest zlib level: 4x quicker than PIL's default for a fifth more bytes, every epoch, in the loop.
        Image.fromarray(grid).save(folder / f"epoch_{trainer.current_epoch:03d}.png", compress_level=1)
        for logger in trainer.loggers:
            _log_image(logger, grid, trainer.global_step)


class LatestCheckpoint(ModelCheckpoint):
    """``ModelCheckpoint`` of the latest epoch that skips an epoch's write when its file is younger than
    ``every_s`` seconds, except after the last epoch (so a finished run's checkpoint is its final state).

    Lightning saves it at the end of an epoch, before it logs the epoch's training metrics. It is written to
    ``last.ckpt.pending`` then, and renamed to ``last.ckpt`` when the next epoch starts or training ends, once
    the loggers have written the epoch's rows: a run killed at any moment resumes from a checkpoint whose
    epochs' rows are all in ``metrics.csv``, and ``last.ckpt`` is never a half-written file.
    """

    def __init__(self, *args: Any, every_s: float = 0.0, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.every_s = float(every_s)
        self._pending: str | None = None  # the checkpoint written to <path>.pending, not yet renamed

    def _due(self, trainer: Any) -> bool:
        if self.every_s <= 0 or trainer.should_stop or trainer.current_epoch + 1 >= (trainer.max_epochs or 0):
            return True
        path = Path(self.dirpath or ".") / f"{self.filename}{self.FILE_EXTENSION}"
        try:
            due = time.time() - path.stat().st_mtime >= self.every_s
        except FileNotFoundError:
            due = True
        # Process 0 decides for all: saving waits at a barrier, so DDP processes that judged the file's age
        # differently would wait for each other for ever.
        return bool(trainer.strategy.broadcast(due, src=0))

    def on_train_epoch_end(self, trainer: Any, pl_module: Any) -> None:
        if self._due(trainer):
            super().on_train_epoch_end(trainer, pl_module)

    def on_validation_end(self, trainer: Any, pl_module: Any) -> None:
        if self._due(trainer):
            super().on_validation_end(trainer, pl_module)

    def _save_checkpoint(self, trainer: Any, filepath: str) -> None:
        super()._save_checkpoint(trainer, filepath + PENDING)
        self._pending = filepath

    def on_train_epoch_start(self, trainer: Any, pl_module: Any) -> None:
        self._put_in_place(trainer)

    def on_train_end(self, trainer: Any, pl_module: Any) -> None:
        self._put_in_place(trainer)

    def _put_in_place(self, trainer: Any) -> None:
        """Rename the pending checkpoint to its name, after the loggers have written what they hold."""
        if self._pending is None:
            return
        for lg in trainer.loggers:
            lg.save()
        if trainer.is_global_zero:  # the process that wrote it
            os.replace(self._pending + PENDING, self._pending)
        self._pending = None


def image_grid(batch: Mapping[str, torch.Tensor]) -> np.ndarray:
    """Rows of RGB | depth | generated | target (the pair's touch) | absolute difference (x4, so small errors
    show) as uint8 [rows*S, 5*S, 3]. ``batch`` holds [N, C, S, S] tensors in [-1, 1]: fake, tactile and optionally
    rgb, depth."""
    fake = batch["fake"].float().clamp(-1, 1)
    n, _, h, w = fake.shape

    def col(x: torch.Tensor | None) -> torch.Tensor:
        if x is None:
            return torch.zeros(n, 3, h, w)
        x = x.float().clamp(-1, 1)
        x = x.expand(-1, 3, -1, -1) if x.shape[1] == 1 else x
        return (x + 1) / 2

    target = batch["tactile"].float().clamp(-1, 1)
    diff = ((fake - target).abs() * 2).clamp(0, 1)  # |a - b| / 2 in [0, 1], times 4
    cols = [col(batch.get("rgb")), col(batch.get("depth")), col(fake), col(target), diff]
    grid = torch.cat([torch.cat(cols, 3)], 0)  # [N, 3, H, 5W]
    grid = grid.permute(0, 2, 3, 1).reshape(n * h, 5 * w, 3)
    return (grid * 255).round().clamp(0, 255).to(torch.uint8).numpy()


def _log_image(logger: Any, grid: np.ndarray, step: int) -> None:
    name = type(logger).__name__
    try:
        if name == "TensorBoardLogger":
            logger.experiment.add_image("val/grid", grid, step, dataformats="HWC")
        elif name == "WandbLogger":
            logger.log_image(key="val/grid", images=[grid], step=step)
    except Exception:  # an image is a convenience; a logger hiccup must not stop training
        pass


class EpochTimes(Callback):
    """Logs each epoch's wall time, seconds, split three ways (in ``metrics.csv`` and any logger):

    - ``time/train_s``: the training batches, from the epoch's start to its end less its validation;
    - ``time/val_s``: the validation loop;
    - ``time/other_s``: from the previous epoch's end to this one's start (checkpoint writing, loader start-up).

    The clock is the host's: queued GPU work counts where the host next waits for it (a validation metric, a
    loss check), so the split is accurate to the length of one queued step.
    """

    @dataclasses.dataclass
    @yaml_defaults(DEFAULTS, node="epoch_times")
    class Config:
        """No settings."""

    def __init__(self, config: Config | None = None):
        self.config = config or self.Config()
        self._epoch_start = 0.0
        self._val_start: float | None = None
        self._val = 0.0
        self._last_end: float | None = None
        self._other = 0.0

    def on_train_epoch_start(self, trainer: Any, pl_module: Any) -> None:
        now = time.perf_counter()
        self._other = now - self._last_end if self._last_end is not None else 0.0
        self._epoch_start, self._val = now, 0.0

    def on_validation_start(self, trainer: Any, pl_module: Any) -> None:
        if not trainer.sanity_checking:
            self._val_start = time.perf_counter()

    def on_validation_end(self, trainer: Any, pl_module: Any) -> None:
        if self._val_start is not None:
            self._val += time.perf_counter() - self._val_start
            self._val_start = None

    def on_train_epoch_end(self, trainer: Any, pl_module: Any) -> None:
        now = time.perf_counter()
        times = {
            "time/train_s": now - self._epoch_start - self._val,
            "time/val_s": self._val,
            "time/other_s": self._other,
        }
        pl_module.log_dict(times, on_step=False, on_epoch=True, rank_zero_only=True)
        self._last_end = now


#: The callbacks a ``callbacks`` config can name, by name.
CALLBACKS: dict[str, type[Any]] = {
    "weight_average": WeightAverage,
    "finite_check": FiniteCheck,
    "discriminator_watch": DiscriminatorWatch,
    "image_grids": ImageGrids,
    "epoch_times": EpochTimes,
}


def build_callbacks(cfg: Mapping[str, Any] | None = None) -> list[Callback]:
    """The callbacks of a ``callbacks`` config (``{name: settings}``, in its order; a null entry is left out);
    None: those of ``conf/callbacks/default.yaml``. An unknown name or setting is a TnfError."""
    if cfg is None:
        from omegaconf import OmegaConf

        cfg = OmegaConf.to_container(OmegaConf.load(Path(conf_dir()) / f"{DEFAULTS}.yaml"), resolve=True)  # type: ignore[assignment]
    callbacks: list[Callback] = []
    for name, settings in dict(cfg or {}).items():
        if settings is None:
            continue
        if name not in CALLBACKS:
            raise TnfError(f"unknown callback {name!r} in callbacks; available: {', '.join(CALLBACKS)}")
        cls = CALLBACKS[name]
        callbacks.append(cls(from_dict(cls.Config, settings, where=f"callbacks.{name}")))
    return callbacks
