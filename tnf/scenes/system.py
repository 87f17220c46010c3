"""``SceneFitSystem``: the LightningModule that fits a learned scene (nerf, hashgrid) to one object's views.

``tnf.scenes.fit.fit_scene`` drives it with a ``lightning.Trainer``. Every training ray and its RGBA target
stay on the device, so a step's random batch is one gather there: the train loader only ticks the steps,
and ``training_step`` draws the batch from the device's default generator, seeded from ``(seed, step)``.
The scene's own sampling (stratified offsets, occupancy-grid points) draws from that generator too, so a fit
resumed from a checkpoint takes exactly the steps of an uninterrupted one.
"""

from __future__ import annotations

import io
import itertools
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, cast

import lightning as L
import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO

from tnf.artifacts import write_bytes
from tnf.cameras import Views, camera_rays
from tnf.errors import NonFiniteLoss, TnfError
from tnf.runtime import step_seed
from tnf.scenes.render import FieldScene, composite
from tnf.scenes.settings import FitSettings

#: Version of the resume checkpoint's ``tnf`` entry; a checkpoint of another version is not resumed from.
#: 2: the fingerprint holds the fit's inputs (``inputs``), which checkpoints of version 1 do not record.
RESUME_FORMAT = 2


class Steps:
    """The train "loader": endless (``max_steps`` ends the fit), yielding 0, 1, 2, ... in each run (unused).
    Batches are drawn on the device in ``training_step``, so it carries no data and a resumed fit needs no
    loader state."""

    def __iter__(self) -> Iterator[int]:
        return itertools.count()


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning checkpoint I/O that writes through ``tnf.artifacts.write_bytes`` (a temporary file in the same
    folder, then ``os.replace``): a process killed while saving leaves the previous checkpoint whole."""

    def save_checkpoint(
        self, checkpoint: dict[str, Any], path: str | os.PathLike[str], storage_options: Any | None = None
    ) -> None:
        buf = io.BytesIO()
        torch.save(checkpoint, buf)
        write_bytes(path, buf.getvalue())


class SceneFitSystem(L.LightningModule):
    """Fits ``scene`` (in place) to the rays of ``views`` with Adam and an exponential learning-rate decay.

    The loss is the mean squared error of the rendered colour against the target composited over the
    batch's background (per ray a random colour with ``random_background``, else the scene's), plus
    ``distortion_weight`` times the scene's distortion loss where it reports one, plus the colour error of a
    coarse pass where the scene has one (NeRF's ``rgb_coarse``).

    Args:
        scene: the scene to fit; its parameters are updated in place.
        views: training views; their rays move to the training device when the fit starts.
        settings: fit settings with every field resolved (``FitSettings.resolved``).
        seed: seed of the step-wise random draws (ray batches, backgrounds, the scene's sampling).
        resume_path: where to write a resumable checkpoint every ``settings.checkpoint_every`` steps; None
            writes none.
        on_step: called as ``on_step(step, loss)`` after every step (0-based step; the last recorded loss).
        inputs: what the fit is made from, as plain data (``tnf.scenes.fit.fit_inputs``: the identity of the
            captured images and the scene's settings); part of the resume checkpoint's ``fingerprint``, so that
            a checkpoint of other inputs is not resumed from. None: the caller vouches that ``views`` and
            ``scene`` are those of any checkpoint at ``resume_path``.
    """

    def __init__(
        self,
        scene: FieldScene,
        views: Views,
        settings: FitSettings,
        seed: int = 0,
        resume_path: str | os.PathLike[str] | None = None,
        on_step: Callable[[int, float], None] | None = None,
        inputs: Any = None,
    ):
        super().__init__()
        self.automatic_optimization = False
        assert settings.steps is not None and settings.batch_rays is not None and settings.lr is not None
        self.scene = scene
        self.settings = settings
        self.steps, self.batch_rays, self.lr = settings.steps, settings.batch_rays, settings.lr
        self._distortion_from = int(round(settings.distortion_start * self.steps))  # first step with it
        self.seed = seed
        self.resume_path = Path(resume_path) if resume_path is not None else None
        self.on_step = on_step
        self.inputs = inputs
        o, d, _ = camera_rays(*views.cameras(), views.width, views.height)
        # Plain attributes, not buffers: they are no part of a checkpoint and Lightning's teardown need not
        # copy them back to the CPU. on_fit_start moves them to the device.
        self.origins = o.reshape(-1, 3)  # [M, 3] metres, world frame
        self.directions = d.reshape(-1, 3)  # [M, 3] unit vectors
        self.targets = views.rgba().reshape(-1, 4)  # [M, 4] RGBA in [0, 1]
        self.num_rays = int(self.origins.shape[0])
        self.loss_log: list[dict[str, Any]] = []  # {"step", "loss"} every log_every steps and at the last
        self.train_seconds = 0.0  # of the earlier parts of a resumed fit, then of the whole fit
        self._started = 0.0
        self._loss = float("nan")  # the last recorded loss
        self._recent = torch.empty(0)  # [log_every] losses of steps _recent_from, ... on the device
        self._recent_from = 0
        self._generator: torch.Generator | None = None
        self._optimisation: tuple[Any, Any] = (None, None)  # Lightning's optimiser and scheduler, per fit

    @property
    def fingerprint(self) -> dict[str, Any]:
        """What a resume checkpoint must match to be resumed from: the fit's inputs (``inputs``: the captured
        images' identity and the scene's settings), the training settings, the seed, the number of rays and
        the shapes of the scene's tensors. Settings that do not change the fitted scene (``checkpoint_every``,
        ``log_every``, ``chunk``, the evaluation's) are left out."""
        s = self.settings
        return {
            "steps": self.steps,
            "batch_rays": self.batch_rays,
            "lr": self.lr,
            "lr_final_factor": s.lr_final_factor,
            "random_background": s.random_background,
            "distortion_weight": s.distortion_weight,
            "distortion_start": s.distortion_start,
            **({"train_kernel": True} if s.train_kernel else {}),
            "seed": self.seed,
            "inputs": self.inputs,
            "rays": self.num_rays,
            "shapes": {k: list(v.shape) for k, v in self.scene.state_dict().items()},
        }

    # -- optimisation -----------------------------------------------------------------------------------
    def configure_optimizers(self) -> Any:
        scene = self.scene
        groups = (
            cast(Any, scene).param_groups(self.lr)
            if hasattr(scene, "param_groups")
            else [{"params": list(scene.parameters())}]
        )
        opt = torch.optim.Adam(groups, lr=self.lr, betas=(0.9, 0.99), eps=1e-15)
        # lr * gamma**steps = lr * lr_final_factor at the last step.
        gamma = self.settings.lr_final_factor ** (1.0 / max(self.steps, 1))
        sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    def train_dataloader(self) -> Steps:
        return Steps()

    def on_fit_start(self) -> None:
        dev = self.device
        self.origins, self.directions = self.origins.to(dev), self.directions.to(dev)
        self.targets = self.targets.to(dev)
        self._recent = torch.empty(self.settings.log_every, device=dev)
        if dev.type == "cuda":
            torch.cuda.init()  # makes sure torch.cuda.default_generators is filled
            index = dev.index if dev.index is not None else torch.cuda.current_device()
            self._generator = torch.cuda.default_generators[index]
        else:
            self._generator = torch.default_generator

    def on_train_start(self) -> None:
        self._started = time.perf_counter()
        self._optimisation = (cast(Any, self.optimizers()), cast(Any, self.lr_schedulers()))
        self._recent_from = self.global_step  # after a resume, the step it resumes at

    def training_step(self, batch: int, batch_idx: int) -> None:
        step, B, dev = self.global_step, self.batch_rays, self.device
        assert self._generator is not None
        # Every draw of this step (batch, backgrounds, the scene's sampling) is a function of (seed, step).
        self._generator.manual_seed(step_seed(self.seed, step))
        scene = self.scene
        scene.update_occupancy(step)
        idx = torch.randint(0, self.num_rays, (B,), device=dev)
        bg = torch.rand(B, 3, device=dev) if self.settings.random_background else scene.background.expand(B, 3)
        gt = composite(self.targets[idx], bg)
        out = scene.render_rays(self.origins[idx], self.directions[idx], bg, perturb=True)
        loss = torch.mean((out["rgb"] - gt) ** 2)
        if self.settings.distortion_weight and "distortion" in out and step >= self._distortion_from:
            loss = loss + self.settings.distortion_weight * out["distortion"].mean()
        if "rgb_coarse" in out:
            loss = loss + torch.mean((out["rgb_coarse"] - gt) ** 2)
        # Manual optimisation: the plain loop's order, with less of Lightning's per-step machinery.
        # loss.backward() rather than manual_backward: the trainer is always fp32 on one device, where
        # manual_backward adds only its hooks (about 0.1 ms a step, 2% of a small CPU step).
        opt, sched = self._optimisation
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        # Kept on the device (no synchronisation); read where the loss is logged or a checkpoint written.
        self._recent[step - self._recent_from] = loss.detach()

    def on_train_batch_end(self, outputs: Any, batch: int, batch_idx: int) -> None:
        step = self.global_step - 1  # the step just taken
        last = step == self.steps - 1
        every = self.settings.checkpoint_every
        log_now = step % self.settings.log_every == 0 or last
        save_now = self.resume_path is not None and every > 0 and (step + 1) % every == 0 and not last
        if log_now or save_now:
            loss = self._read_losses(step)  # a diverged fit stops here, before it overwrites a checkpoint
            if log_now:
                self._loss = loss
                self.loss_log.append({"step": step, "loss": loss})
        if self.on_step is not None:
            self.on_step(step, self._loss)
        if save_now:
            assert self.resume_path is not None
            self.trainer.save_checkpoint(self.resume_path)

    def on_train_end(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        self.train_seconds += time.perf_counter() - self._started
        # The rays are not needed any more; release the device memory now rather than at garbage collection.
        empty = torch.empty(0, 3)
        self.origins, self.directions, self.targets = empty, empty, torch.empty(0, 4)

    def _read_losses(self, step: int) -> float:
        """The loss of ``step``, the step just taken; ``NonFiniteLoss`` names the first NaN or infinite loss
        since the last read (reads come at least every ``log_every`` steps, the buffer's length)."""
        recent = self._recent[: step - self._recent_from + 1].cpu()
        bad = (~torch.isfinite(recent)).nonzero()
        if bad.numel():
            raise NonFiniteLoss(
                f"non-finite scene fitting loss (NaN or Inf) at step {self._recent_from + int(bad[0])}; the fit "
                f"stopped ({self.resume_note()}); lower fit.lr or check the capture's images"
            )
        self._recent_from = step + 1
        return float(recent[-1])

    def resume_note(self) -> str:
        """Where the fit can resume from, for error messages."""
        if self.resume_path is not None and self.resume_path.is_file():
            return f"the last good checkpoint is {self.resume_path}"
        return "no checkpoint was saved yet"

    # -- checkpoints ------------------------------------------------------------------------------------
    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint["tnf"] = {
            "format": RESUME_FORMAT,
            "kind": "scene_fit",
            "fit": self.fingerprint,
            "log": list(self.loss_log),
            "train_seconds": self.train_seconds + time.perf_counter() - self._started,
        }

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        meta = checkpoint["tnf"]
        self.loss_log = list(meta["log"])
        self.train_seconds = float(meta["train_seconds"])
        if self.loss_log:
            self._loss = float(self.loss_log[-1]["loss"])

    def resumable(self, path: Path) -> tuple[bool, str]:
        """Whether the checkpoint at ``path`` can be resumed from, and if not why: it must have been written by
        this tnf version's fit with the same ``fingerprint`` (inputs, training settings, seed, ray count and
        tensor shapes). With ``inputs`` None nothing checks that the checkpoint was made from these views."""
        try:
            ckpt = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
        except Exception as e:  # torch raises several types for files that are not checkpoints
            return False, f"unreadable ({str(e).splitlines()[0][:200]})"
        meta = ckpt.get("tnf") if isinstance(ckpt, dict) else None
        if not isinstance(meta, dict) or meta.get("kind") != "scene_fit" or meta.get("format") != RESUME_FORMAT:
            return False, "written by another tnf version"
        fit = meta.get("fit")
        if fit != self.fingerprint:
            return False, other_inputs(fit, self.fingerprint) or "written by a fit with other settings"
        return True, ""


def lightning_device(device: str) -> tuple[str, int | list[int]]:
    """Lightning ``(accelerator, devices)`` for a torch device string: ``cpu``, ``cuda`` (the current GPU) or
    ``cuda:N``."""
    dev = torch.device(device)
    if dev.type == "cpu":
        return "cpu", 1
    if dev.type == "cuda":
        return "gpu", [dev.index if dev.index is not None else torch.cuda.current_device()]
    raise TnfError(f"device must be cpu, cuda or cuda:N, got {device!r}")


def other_inputs(old: Any, new: dict[str, Any]) -> str | None:
    """Why a checkpoint of fingerprint ``old`` was made from other inputs than a fit of fingerprint ``new``
    (``inputs`` as ``fit_inputs`` makes them: ``capture``, ``scene``); None when the inputs are the same or
    unknown."""
    a = old.get("inputs") if isinstance(old, dict) else None
    b = new.get("inputs")
    if not isinstance(a, dict) or not isinstance(b, dict) or a == b:
        return None
    if a.get("capture") != b.get("capture"):
        return "made from other captured images"
    if a.get("scene") != b.get("scene"):
        return "made with other scene settings"
    return "made from other inputs"
