"""``GeneratorSystem``: the one LightningModule that trains any registered generator.

It builds the generator from its registry name and config (both stored in the checkpoint, never a class
path, so a checkpoint loads wherever the generator's package is installed), runs the generator's own GAN
step with Lightning's manual optimisation (mixed precision and gradient scaling come from the trainer's
``precision``), applies the learning-rate schedule (constant, then linear decay to zero) and validates with
``tnf.metrics`` (L1, SSIM, MSE).

With ``ema_decay`` it also holds an exponential moving average of the generator's weights (``generator_ema``),
which the ``WeightAverage`` callback updates after every training step. The average is what validates and
generates; checkpoints hold both, and ``from_checkpoint`` loads the average unless asked for the trained weights.

The finiteness check, the discriminator watcher and the image grids are callbacks too
(``tnf.generators.callbacks``), which read ``finite_check_every`` and ``grid_rows`` from the system's
hyper-parameters.
"""

from __future__ import annotations

import copy
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import lightning as L
import torch

from tnf import __version__, metrics
from tnf.artifacts import CACHE_VERSION
from tnf.data.dataset import mirror_batch, unmirror_channels
from tnf.errors import TnfError
from tnf.generators.base import Generator
from tnf.registry import GENERATORS, config_to_dict, split_spec

#: Version of the checkpoints ``GeneratorSystem`` writes (``tnf.artifacts.CACHE_VERSION``); loading another one is
#: an error.
CHECKPOINT_FORMAT = CACHE_VERSION

#: Prefix of the averaged generator's weights in a checkpoint's state dict (``ema_decay``).
AVERAGE_PREFIX = "generator_ema."


class _LightningOptimisation:
    """The ``Optimisation`` a generator sees inside Lightning: wrapped optimisers and ``manual_backward``."""

    def __init__(self, system: GeneratorSystem):
        self.system = system

    def optimizers(self) -> Sequence[Any]:
        opts = self.system.optimizers()
        return opts if isinstance(opts, list) else [opts]

    def backward(self, loss: torch.Tensor) -> None:
        self.system.manual_backward(loss)


def generator_config(spec: Mapping[str, Any] | str) -> tuple[str, Any]:
    """A generator's name and its ``{name, **params}`` validated into the generator's Config."""
    name, params = split_spec(spec, "generator")
    return name, GENERATORS.config(name, params)


def generator_spec(spec: Mapping[str, Any] | str) -> dict[str, Any]:
    """A generator's ``{name, **params}`` with every field filled in (validated), as plain JSON data."""
    name, config = generator_config(spec)
    return {"name": name, **config_to_dict(config)}


def compile_networks(generator: torch.nn.Module, mode: str | None = None) -> None:
    """Run each network of ``generator`` (its ``net_*`` children) through ``torch.compile`` (with ``mode``, one of
    torch.compile's, such as ``reduce-overhead``), in place: the training step stays eager, and the state dict
    keeps its keys, so checkpoints are the same with and without."""
    for name, child in generator.named_children():
        if name.startswith("net_"):
            child.compile(mode=mode)


# Slack on the [-1, 1] range of a generator's images (a tanh in bf16 rounds to exactly 1).
RANGE_SLACK = 1e-3


def checked_images(fake: Any, batch: Mapping[str, torch.Tensor], name: str) -> torch.Tensor:
    """``fake`` when it is valid output of generator ``name`` for ``batch``: a float tensor [B, 3, H, W] (B and
    H, W those of ``batch``'s tactile or background images), finite, in [-1, 1]. Else a one-line TnfError that
    says what is wrong and what ``generate()`` must return (each check waits for the device once)."""
    must = f"; Generator.generate() of {name!r} must return float images [B, 3, H, W] in [-1, 1] (end in tanh)"
    if not isinstance(fake, torch.Tensor):
        raise TnfError(f"generator {name!r} returned a {type(fake).__name__}, not a tensor{must}")
    if not fake.is_floating_point():
        raise TnfError(f"generator {name!r} returned {fake.dtype} images{must}")
    ref = batch.get("tactile", batch.get("background"))
    want = (next(iter(batch.values())).shape[0], 3, *(ref.shape[-2:] if ref is not None else fake.shape[-2:]))
    if tuple(fake.shape) != want:
        raise TnfError(f"generator {name!r} returned images of shape {list(fake.shape)}, expected {list(want)}{must}")
    finite = torch.isfinite(fake)
    if not bool(finite.all()):
        raise TnfError(
            f"generator {name!r} returned non-finite images ({int((~finite).sum())} NaN or Inf values){must}"
        )
    lo, hi = (float(v) for v in torch.aminmax(fake.detach().float()))
    if lo < -1 - RANGE_SLACK or hi > 1 + RANGE_SLACK:
        raise TnfError(f"generator {name!r} returned images in [{lo:.3g}, {hi:.3g}]{must}")
    return fake


class GeneratorSystem(L.LightningModule):
    """Trains and validates the generator named in ``generator`` (``{"name": ..., **config}``).

    Args:
        generator: registry name and config of the generator, or the ``(name, Config)`` pair of
            :func:`generator_config`, built from as it is (not checked again).
        epochs: total training epochs (for the learning-rate schedule).
        decay_epochs: the last ``decay_epochs`` epochs decay the learning rate linearly to zero (pix2pix).
        grid_rows: validation pairs shown in the per-epoch image grid (``ImageGrids``; 0: none).
        finite_check_every: ``FiniteCheck`` checks the losses for NaN/Inf every this many steps (each check
            synchronises with the GPU); they are always checked before validation and at the end of an epoch.
        ema_decay: keep an exponential moving average of the generator's weights with this decay per
            training step (updated by ``WeightAverage``), and validate and generate with it; None keeps none.
        compile_nets: run the generator's networks through ``torch.compile`` (True, or one of its modes by
            name); a speed setting that checkpoints do not record.
    """

    ema_updates: torch.Tensor  # a buffer, with ema_decay only

    def __init__(
        self,
        generator: Mapping[str, Any] | str | tuple[str, Any],
        epochs: int = 200,
        decay_epochs: int = 100,
        grid_rows: int = 8,
        finite_check_every: int = 50,
        ema_decay: float | None = None,
        compile_nets: bool | str = False,
    ):
        super().__init__()
        # The generator is built from this Config, not checked again.
        name, config = generator if isinstance(generator, tuple) else generator_config(generator)
        spec = {"name": name, **config_to_dict(config)}
        self.compile_nets = compile_nets  # a speed setting, not a hyperparameter: checkpoints do not record it
        if decay_epochs < 0 or decay_epochs > epochs:
            raise TnfError(f"decay_epochs must be in [0, epochs={epochs}], got {decay_epochs}")
        ema_decay = _decay(ema_decay)
        self.save_hyperparameters(
            {
                "generator": spec,
                "epochs": epochs,
                "decay_epochs": decay_epochs,
                "grid_rows": grid_rows,
                "finite_check_every": finite_check_every,
                "ema_decay": ema_decay,
            }
        )
        self.automatic_optimization = False
        self.generator: Generator = GENERATORS.get(name)(config)
        # The average is a copy that no optimiser or gradient touches; its update count is checkpointed with it.
        self.generator_ema: Generator | None = None
        if ema_decay is not None:
            self.generator_ema = copy.deepcopy(self.generator).requires_grad_(False)
            self.register_buffer("ema_updates", torch.zeros((), dtype=torch.long))
        self._opt = _LightningOptimisation(self)
        self._epoch_samples = 0  # pairs this process trained on in the current epoch
        self._val: dict[str, list[torch.Tensor]] = {}

    @property
    def generator_name(self) -> str:
        return self.hparams["generator"]["name"]

    @property
    def generating(self) -> Generator:
        """The generator that validates and generates: the weights' average where one is kept."""
        return self.generator_ema if self.generator_ema is not None else self.generator

    def configure_model(self) -> None:
        # Channels-last: faster convolutions with cuDNN and oneDNN (docs/decisions/train_channels_last.md); the
        # datasets' float batches are channels-last already, and the state dict is the same in either layout.
        # Converted here, before the strategy wraps the model: DDP lays out its gradient buckets after the
        # parameters as they are then (parameters converted later make every step copy gradients).
        self.to(memory_format=torch.channels_last)
        if self.compile_nets:
            mode = self.compile_nets if isinstance(self.compile_nets, str) else None
            compile_networks(self.generator, mode)

    # -- generation -------------------------------------------------------------------------------------
    def forward(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Tactile images [B, 3, H, W] in [-1, 1] for a batch of conditions."""
        return self.generating.generate(batch)

    @torch.no_grad()
    def generate(self, batch: dict[str, torch.Tensor], mirror: Sequence[int] | None = None) -> torch.Tensor:
        """Generate in eval mode without gradients (dropout stays on where the generator keeps it).

        With ``mirror`` (the sensor's ``Sensor.mirror_channels``), each image is the mean of the generator's
        image and, mirrored back, its image of the mirrored conditions (``tnf.data.mirror_batch``): a sensor
        with that symmetry makes the two alike, so the mean is the generator's estimate from both views.
        """
        was = self.training
        self.eval()
        try:
            fake = checked_images(self.generating.generate(batch), batch, self.generator_name)
            if mirror is None:
                return fake
            flipped = self.generating.generate({**batch, **mirror_batch(batch, mirror)})
            back = mirror_batch({"tactile": flipped}, unmirror_channels(mirror))["tactile"]
            return (fake + back) / 2
        finally:
            self.train(was)

    # -- optimisation -----------------------------------------------------------------------------------
    def configure_optimizers(self) -> Any:
        opts = self.generator.configure_optimizers()
        epochs, decay = self.hparams["epochs"], self.hparams["decay_epochs"]
        constant = epochs - decay

        def factor(epoch: int) -> float:  # 1 for `constant` epochs, then linearly towards 0
            return 1.0 - max(0, epoch + 1 - constant) / float(decay + 1)

        scheds = [torch.optim.lr_scheduler.LambdaLR(o, factor) for o in opts]
        return opts, scheds

    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> dict[str, torch.Tensor]:
        """One step of the generator's game; returns its losses (scalars), which the callbacks receive."""
        losses = self.generator.training_step(batch, self._opt)
        bs = next(iter(batch.values())).shape[0]
        self.log_dict({f"train/{k}": v for k, v in losses.items()}, on_step=True, on_epoch=True, batch_size=bs)
        self._epoch_samples += bs
        for k in ("loss_g", "loss_d"):
            if k in losses:
                self.log(k, losses[k], prog_bar=True, on_step=True, on_epoch=False, logger=False, batch_size=bs)
        # Detached, as the generator's contract asks: a DDP wrapper searches the step's outputs for a graph.
        return {k: v.detach() for k, v in losses.items()}

    def reset_average(self) -> None:
        """Start the average afresh from the generator's current weights (no-op without ``ema_decay``)."""
        if self.generator_ema is None:
            return
        self.generator_ema.load_state_dict(self.generator.state_dict())
        self.ema_updates.zero_()

    def on_train_epoch_start(self) -> None:
        self._epoch_samples = 0

    def on_train_epoch_end(self) -> None:
        # Pairs trained on this epoch by all processes, and by this one (process 0's in the logs): with DDP each
        # process trains on its own shard, so rank_samples is samples / world size. Summed here, in a hook every
        # process runs in the same order (a sync_dist metric is summed lazily, when a callback of process 0
        # alone reads it first, and the processes' collectives would then no longer match).
        n = torch.tensor(float(self._epoch_samples), device=self.device)
        total = self.trainer.strategy.reduce(n.clone(), reduce_op="sum") if self.trainer.world_size > 1 else n
        self.log("train/samples", total, on_epoch=True, on_step=False)
        self.log("train/rank_samples", n, on_epoch=True, on_step=False)
        opts = self._opt.optimizers()
        for name, o in zip(self.generator.optimizer_names, opts):  # the rate this epoch trained with
            self.log(f"lr/{name}", o.param_groups[0]["lr"], on_epoch=True, on_step=False)
        scheds = self.lr_schedulers()
        for s in scheds if isinstance(scheds, list) else [scheds]:
            if s is not None:
                s.step()

    # -- validation -------------------------------------------------------------------------------------
    def on_validation_epoch_start(self) -> None:
        self._val = {"l1": [], "ssim": [], "mse": []}

    def validation_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> dict[str, torch.Tensor]:
        """Scores the generated images of a batch; returns them (``fake``, [B, 3, H, W] in [-1, 1])."""
        fake = checked_images(self.generating.generate(batch), batch, self.generator_name).float()
        real = batch["tactile"].float()
        self._val["l1"].append((fake - real).abs().flatten(1).mean(1))
        self._val["ssim"].append(metrics.ssim(fake, real))
        self._val["mse"].append(metrics.mse(fake, real))
        return {"fake": fake}

    def on_validation_epoch_end(self) -> None:
        if not self._val["l1"]:
            return
        vals = {f"val_{k}": torch.cat(v).mean() for k, v in self._val.items()}
        self.log_dict(vals, prog_bar=True, sync_dist=True)

    # -- checkpoints ------------------------------------------------------------------------------------
    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint["tnf"] = {
            "format": CHECKPOINT_FORMAT,
            "kind": "generator",
            "generator": dict(self.hparams["generator"]),
            "tnf_version": __version__,
            # The distribution that registers the generator: a plugin's, named when it is not installed.
            "origin": GENERATORS.entry(self.generator_name).origin,
        }

    @classmethod
    def from_checkpoint(
        cls,
        path: str | os.PathLike[str],
        device: str | torch.device = "cpu",
        expected: str | None = None,
        generator_overrides: Mapping[str, Any] | None = None,
        averaged: bool = True,
        **kw: Any,
    ) -> GeneratorSystem:
        """Build the system a checkpoint was saved from and load its generator's weights (not its optimiser
        state): the weights' average where the checkpoint holds one (``ema_decay``), else as trained.

        ``expected``: the generator name the caller needs (a checkpoint of another one is an error).
        ``generator_overrides``: generator config fields to change (e.g. ``{"lr": 1e-4}`` for fine-tuning);
        ``averaged=False`` loads the trained weights rather than their average (to compare the two); ``kw``
        override the other hyper-parameters (epochs, decay_epochs, grid_rows, finite_check_every, ema_decay).
        A system that keeps an average starts it from the loaded weights.
        """
        ckpt = read_checkpoint(path)
        meta = ckpt["tnf"]
        saved = dict(meta["generator"])
        spec = {**saved, **dict(generator_overrides or {})}
        if expected is not None and spec.get("name") != expected:
            raise TnfError(f"checkpoint {path} holds generator {spec.get('name')!r}, expected {expected!r}")
        origin = meta.get("origin")
        if spec.get("name") not in GENERATORS and origin:
            raise TnfError(
                f"checkpoint {path} holds generator {spec.get('name')!r} of the package {origin!r}, which is not "
                f"installed here; install it (pip install {origin}) to load the model"
            )
        hp = {k: v for k, v in ckpt.get("hyper_parameters", {}).items() if k != "generator"}
        hp.update(kw)
        system = cls(spec, **hp)
        state = ckpt["state_dict"]
        has_average = any(k.startswith(AVERAGE_PREFIX) for k in state)
        prefix = AVERAGE_PREFIX if averaged and has_average else "generator."
        weights = {k.removeprefix(prefix): v for k, v in state.items() if k.startswith(prefix)}
        missing, unexpected = _load_state(system.generator, weights)
        if missing or unexpected:
            raise TnfError(
                f"checkpoint {path} does not fit generator {spec.get('name')!r} of this tnf version "
                f"(missing {missing[:3]}, unexpected {unexpected[:3]}); retrain or use the tnf version that wrote it"
            )
        system.reset_average()
        return system.to(device)


def _decay(value: Any) -> float | None:
    """``ema_decay`` as a float in (0, 1), or None; anything else is a TnfError."""
    if value is None:
        return None
    try:
        decay = float(value)
    except (TypeError, ValueError):
        decay = float("nan")
    if isinstance(value, bool) or not 0.0 < decay < 1.0:
        raise TnfError(f"ema_decay must be in (0, 1) (e.g. 0.999), or null for no average; got {value!r}")
    return decay


def _load_state(module: torch.nn.Module, state: Mapping[str, torch.Tensor]) -> tuple[list[str], list[str]]:
    try:
        res = module.load_state_dict(state, strict=False)
    except RuntimeError as e:  # shape mismatches
        first = str(e).splitlines()[1:2]
        return [first[0].strip() if first else "shapes differ"], []
    return list(res.missing_keys), list(res.unexpected_keys)


def read_checkpoint(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Load a generator checkpoint on the CPU; not a tnf generator checkpoint or another format -> TnfError."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise TnfError(f"generator checkpoint not found: {p}")
    try:
        ckpt = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises several types for files that are not checkpoints
        raise TnfError(f"cannot read generator checkpoint {p}: {str(e).splitlines()[0][:200]}") from None
    meta = ckpt.get("tnf") if isinstance(ckpt, dict) else None
    if not isinstance(meta, dict) or meta.get("kind") != "generator" or "state_dict" not in ckpt:
        raise TnfError(f"{p} is not a tnf generator checkpoint (written by `tnf train`)")
    if meta.get("format") != CHECKPOINT_FORMAT:
        raise TnfError(
            f"checkpoint {p} has format {meta.get('format')!r} (tnf {meta.get('tnf_version')}); this tnf reads "
            f"format {CHECKPOINT_FORMAT}"
        )
    return ckpt


def load_generator(
    path: str | os.PathLike[str],
    device: str | torch.device = "cpu",
    expected: str | None = None,
    averaged: bool = True,
) -> GeneratorSystem:
    """A trained generator from a checkpoint, in eval mode on ``device``; ``system.generate(batch)`` runs it.

    It generates with the weights' average where the checkpoint holds one; ``averaged=False`` with the weights
    as trained. Its networks are channels-last, as in training and its validation: 0.64x of the time of
    contiguous ones to generate on a CPU, the images within 1e-6."""
    system = GeneratorSystem.from_checkpoint(path, device, expected=expected, averaged=averaged, ema_decay=None)
    return system.to(memory_format=torch.channels_last).eval()
