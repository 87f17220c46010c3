"""Fitting a scene to one object's captured views, and measuring it on the held-out views.

``fit_scene`` trains on random batches of rays drawn from all training images of a ``transforms.json``
(instant-ngp / nerfstudio format, RGBA images composited over a known background): a ``lightning.Trainer``
runs ``tnf.scenes.system.SceneFitSystem``, which saves resumable checkpoints. ``evaluate_scene`` then
renders the views of ``transforms_test.json`` and reports PSNR, SSIM and the depth error against
ground-truth depth where the dataset has it.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import torch

from tnf.artifacts import MANIFEST, files_digest, identity, read_json, write_json
from tnf.cameras import Views, camera_rays, read_views
from tnf.errors import TnfError
from tnf.metrics import ssim
from tnf.registry import SCENES, split_spec
from tnf.runtime import ignore_lightning_deprecations, lightning_logs_once
from tnf.scenes import save_scene
from tnf.scenes.render import FieldScene, composite
from tnf.scenes.settings import FitSettings

if TYPE_CHECKING:
    import lightning

log = logging.getLogger(__name__)


def bound_from_cameras(views: Views) -> float:
    """Half-size (metres) of a cube around the origin that holds the object, from the camera setup.

    The object is framed by every camera, so it lies within the nearest camera's view cone; the cube's
    half-size is that camera's distance to the origin times the tangent of its narrowest half field of view.
    """
    c2w, intrinsics = views.cameras()
    dist = c2w[:, :3, 3].norm(dim=-1)
    fx, fy = intrinsics[:, 0], intrinsics[:, 1]
    half = torch.minimum(torch.atan(0.5 * views.width / fx), torch.atan(0.5 * views.height / fy))
    b = (dist * torch.tan(half)).min()
    return float(b)


def object_size(views: Views) -> float | None:
    """Largest extent (metres) of the axis-aligned box around the ground-truth depth points; None without depth."""
    if views.depth is None:
        return None
    c2w, intrinsics = views.cameras()
    depth = torch.from_numpy(views.depth)
    pts = []
    for k in range(len(views)):
        o, d, z = camera_rays(c2w[k : k + 1], intrinsics[k], views.width, views.height)
        zk = depth[k]
        m = zk > 0
        if m.any():
            dist = zk[m] / z[0][m]
            pts.append(o[0][m] + dist.unsqueeze(-1) * d[0][m])
    if not pts:
        return None
    p = torch.cat(pts)
    return float((p.amax(0) - p.amin(0)).max())


def build_scene(spec: dict[str, Any], views: Views) -> FieldScene:
    """Build a scene from ``{"name": kind, **config}``; a null ``bound`` comes from the cameras."""
    name, params = split_spec(spec, "scene")
    if params.get("bound") is None:
        params["bound"] = bound_from_cameras(views)
    scene = SCENES.build({"name": name, **params})
    if not isinstance(scene, FieldScene):
        raise TnfError(f"scene {name!r} cannot be fitted (it is not a learned field)")
    return scene


def fit_inputs(scene_spec: dict[str, Any], capture_dir: str | os.PathLike[str]) -> dict[str, Any]:
    """What a fit of ``scene_spec`` to the capture in ``capture_dir`` is made from, as plain data for its resume
    checkpoint (``SceneFitSystem``'s ``inputs``): ``scene``, the scene's settings, and ``capture``, the identity
    of the captured images: the capture item's ``config_hash`` (its manifest), or for a folder without a
    manifest its files' names, sizes and times (``tnf.artifacts.files_digest``)."""
    folder = Path(capture_dir)
    manifest = folder / MANIFEST
    key = read_json(manifest, "manifest").get("config_hash") if manifest.is_file() else None
    capture = f"item:{key}" if key else f"files:{files_digest(folder)}"
    return {"scene": identity(scene_spec), "capture": capture}


def use_kernel(model: Any, settings: FitSettings) -> None:
    """Set the hash encoding of ``model`` (a hash-grid scene) to train by Warp kernels when
    ``settings.train_kernel`` is on; a TnfError when it is on for a scene without one (nerf)."""
    from tnf.scenes.encoding import HashEncoding

    encoding = getattr(model, "encoding", None)
    if not isinstance(encoding, HashEncoding):
        if settings.train_kernel:
            raise TnfError(f"fit.train_kernel trains a hash grid's encoding; this {type(model).__name__} has none")
        return
    encoding.train_kernel = settings.train_kernel


def fit_scene(
    scene: FieldScene,
    views: Views,
    settings: FitSettings,
    kind: str,
    device: str = "cpu",
    resume_path: str | os.PathLike[str] | None = None,
    on_step: Callable[[int, float], None] | None = None,
    seed: int = 0,
    inputs: Any = None,
) -> dict[str, Any]:
    """Train ``scene`` on ``views`` in place; returns ``{"steps", "train_seconds", "final_loss", "log"}``.

    A ``lightning.Trainer`` runs ``tnf.scenes.system.SceneFitSystem`` for ``steps`` steps of ``batch_rays``
    random rays on ``device`` (``cpu``, ``cuda``, ``cuda:N``). ``resume_path``: a checkpoint file written
    atomically every ``checkpoint_every`` steps (scene, optimiser, scheduler, step, loss log, training
    seconds); when one of a fit with the same inputs and settings exists, training resumes from it and ends
    exactly as an uninterrupted fit would; another is removed, with a warning that says why. It is removed
    when training completes. ``inputs``: what the fit is made from (``fit_inputs``), which the checkpoint
    must match; None checks only the settings, ray count and tensor shapes. ``on_step(step, loss)`` is called
    after every step (progress bars). ``train_seconds``: wall time of the training steps (all parts of a
    resumed fit). ``log``: ``{"step", "loss"}`` every ``log_every`` steps and at the last. The scene ends on
    ``device`` in eval mode. A NaN or infinite loss raises ``tnf.errors.NonFiniteLoss`` naming the step.
    """
    from lightning.pytorch.utilities.exceptions import SIGTERMException

    from tnf.scenes.system import SceneFitSystem

    s = settings.resolved(kind)
    use_kernel(scene, s)
    system = SceneFitSystem(scene, views, s, seed=seed, resume_path=resume_path, on_step=on_step, inputs=inputs)
    resume = Path(resume_path) if resume_path else None
    ckpt_path = None
    if resume is not None and resume.is_file():
        ok, why = system.resumable(resume)
        if ok:
            ckpt_path = str(resume)
        else:
            log.warning("not resuming from %s (%s): the fit starts afresh", resume, why)
            resume.unlink()
    try:
        with _quiet_lightning():
            # resumable() has read the checkpoint with weights_only=True already.
            _trainer(s, device).fit(system, ckpt_path=ckpt_path)
    except SystemExit as e:
        # Lightning ends a fit on Ctrl+C with exit(1), and on SIGTERM with an exit of status 0 (success).
        if isinstance(e.__context__, KeyboardInterrupt):
            raise e.__context__ from None
        if isinstance(e, SIGTERMException):
            raise TnfError(f"scene fitting stopped by SIGTERM; {system.resume_note()}") from None
        raise
    # Lightning's teardown leaves the module on the CPU.
    scene.to(device).eval()
    if resume is not None:
        resume.unlink(missing_ok=True)
    records = system.loss_log
    return {
        "steps": s.steps,
        "train_seconds": system.train_seconds,
        "final_loss": records[-1]["loss"] if records else None,
        "log": records,
    }


def _trainer(settings: FitSettings, device: str) -> lightning.Trainer:
    """A Trainer for ``settings.steps`` steps on ``device`` with nothing that costs time per step: no logger,
    progress bar (callers draw their own through ``on_step``), model summary, validation or checkpoint
    callback (``SceneFitSystem`` writes its resume checkpoint itself, atomically)."""
    import lightning as L

    from tnf.scenes.system import AtomicCheckpointIO, lightning_device

    assert settings.steps is not None
    accelerator, devices = lightning_device(device)
    return L.Trainer(
        accelerator=accelerator,
        devices=devices,
        max_steps=settings.steps,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        limit_val_batches=0,
        plugins=[AtomicCheckpointIO()],
    )


@contextlib.contextmanager
def _quiet_lightning() -> Iterator[None]:
    """Silence Lightning's per-fit notices (available devices, "max_steps reached"): a stage fits many
    objects and draws its own progress. Also Lightning's own deprecations
    (``tnf.runtime.ignore_lightning_deprecations``); its warnings print once (``tnf.runtime.lightning_logs_once``)."""
    lightning_logs_once()
    logger = logging.getLogger("lightning.pytorch")
    level = logger.level
    logger.setLevel(logging.WARNING)
    try:
        with warnings.catch_warnings():
            ignore_lightning_deprecations()
            yield
    finally:
        logger.setLevel(level)


def psnr(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-image PSNR (dB), [B], of [B, H, W, 3] images in [0, 1]."""
    mse = ((pred - target) ** 2).flatten(1).mean(1)
    return -10.0 * torch.log10(mse.clamp_min(1e-10))


@torch.no_grad()
def evaluate_scene(scene: FieldScene, views: Views, chunk: int | None, size: float | None = None) -> dict[str, Any]:
    """Render ``views`` and compare: PSNR (dB), SSIM, depth error (metres and relative to ``size``).

    Ground truth is composited over the scene's background. The depth error is the median over pixels
    where the ground truth sees the object (rendered depth 0 there counts as a full miss).
    Returns the metrics and the renders (``rgb`` [N, H, W, 3], ``depth`` [N, H, W], ``gt`` [N, H, W, 3]).
    """
    scene.eval()
    dev = scene.background.device
    c2w, intrinsics = views.cameras()
    rgb, depth = [], []
    t0 = time.perf_counter()
    for k in range(len(views)):
        r = scene.render_rgbd(c2w[k : k + 1], intrinsics[k], views.width, views.height, chunk)
        rgb.append(r["rgb"].cpu())
        depth.append(r["depth"].cpu())
    if dev.type == "cuda":
        torch.cuda.synchronize()
    seconds = time.perf_counter() - t0
    pred = torch.cat(rgb)
    pdepth = torch.cat(depth)
    gt = composite(views.rgba(), scene.background.cpu())
    p = psnr(pred, gt)
    to_net = lambda x: x.permute(0, 3, 1, 2) * 2 - 1  # noqa: E731  metrics take [-1, 1] images
    s = ssim(to_net(pred), to_net(gt))
    metrics: dict[str, Any] = {
        "psnr": float(p.mean()),
        "ssim": float(s.mean()),
        "psnr_per_view": [round(float(x), 3) for x in p],
        "test_views": int(pred.shape[0]),
        "render_seconds_per_view": seconds / max(pred.shape[0], 1),
    }
    if views.depth is not None:
        true_depth = torch.from_numpy(views.depth)
        m = true_depth > 0
        if m.any():
            err = (pdepth[m] - true_depth[m]).abs()
            metrics["depth_error_median_m"] = float(err.median())
            if size:
                metrics["depth_error_median_rel"] = float(err.median()) / size
    return {"metrics": metrics, "rgb": pred, "depth": pdepth, "gt": gt}


def preview_strip(gt: torch.Tensor, rgb: torch.Tensor, depth: torch.Tensor, n: int) -> np.ndarray:
    """uint8 [n*H, 3*W, 3] image: one row per view, columns ground truth | rendered RGB | rendered depth.

    Depth is shown in grey, near = bright, normalised per view over the object's pixels; empty = black.
    """
    rows = []
    for k in range(min(n, gt.shape[0])):
        d = depth[k]
        m = d > 0
        if m.any():
            lo, hi = float(d[m].min()), float(d[m].max())
            g = torch.where(m, 1.0 - 0.8 * (d - lo) / max(hi - lo, 1e-9), torch.zeros_like(d))
        else:
            g = torch.zeros_like(d)
        rows.append(torch.cat([gt[k], rgb[k], g.unsqueeze(-1).expand(-1, -1, 3)], dim=1))
    img = torch.cat(rows, dim=0) if rows else torch.zeros(1, 3, 3)
    return (img.clamp(0, 1) * 255).round().to(torch.uint8).numpy()


def fit_object(
    scene_spec: dict[str, Any],
    capture_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    settings: FitSettings,
    device: str = "cpu",
    resume_path: str | os.PathLike[str] | None = None,
    on_step: Callable[[int, float], None] | None = None,
    seed: int = 0,
    size_m: float | None = None,
) -> dict[str, Any]:
    """Fit one object from ``capture_dir`` (``transforms.json``, ``transforms_test.json``) into ``out_dir``.

    Writes ``scene.pt``, ``metrics.json`` and ``preview.png``; returns the metrics. ``size_m``: the object's
    size for the relative depth error (default: the extent of the ground-truth depth points).
    """
    capture_dir = Path(capture_dir)
    kind, _ = split_spec(scene_spec, "scene")
    train = read_views(capture_dir / "transforms.json")
    torch.manual_seed(seed)
    scene = build_scene(scene_spec, train)
    if settings.carve and hasattr(scene, "carve"):
        # Empty space seen by the cameras is skipped from the first step (visual hull of the RGBA masks).
        cast(Any, scene).carve(*train.cameras(), train.rgba()[..., 3])
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    inputs = fit_inputs(scene_spec, capture_dir)
    info = fit_scene(scene, train, settings, kind, device, resume_path, on_step, seed, inputs)
    return write_fit(scene, kind, train, capture_dir, out_dir, settings, info, device, size_m)


def write_fit(
    scene: FieldScene,
    kind: str,
    train: Views,
    capture_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    settings: FitSettings,
    info: dict[str, Any],
    device: str = "cpu",
    size_m: float | None = None,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Evaluate a fitted ``scene`` on the held-out views of ``capture_dir`` and write ``scene.pt``,
    ``metrics.json`` and ``preview.png`` into ``out_dir``; returns the metrics. ``info``: what ``fit_scene``
    returned; ``extra``: more metrics (``tnf.scenes.batched`` adds the group's figures)."""
    from PIL import Image

    capture_dir, out_dir = Path(capture_dir), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    test_file = capture_dir / "transforms_test.json"
    test = read_views(test_file, settings.eval_views) if test_file.is_file() else None
    size = size_m or object_size(train)
    metrics: dict[str, Any] = {
        "scene": kind,
        "steps": info["steps"],
        "train_seconds": info["train_seconds"],
        "final_loss": info["final_loss"],
        "bound_m": scene.bound,
        "object_size_m": size,
        "train_views": len(train),
        "resolution": [train.width, train.height],
        **(extra or {}),
    }
    if test is not None:
        ev = evaluate_scene(scene, test, settings.chunk, size)
        metrics.update(ev["metrics"])
        strip = preview_strip(ev["gt"], ev["rgb"], ev["depth"], settings.preview_views)
        Image.fromarray(strip).save(out_dir / "preview.png")
    if device.startswith("cuda"):
        metrics["peak_gpu_memory_gib"] = torch.cuda.max_memory_allocated() / 2**30
    metrics["train_log"] = info["log"]
    save_scene(
        scene, out_dir, extra={"object_size_m": size, "metrics": {k: v for k, v in metrics.items() if k != "train_log"}}
    )
    write_json(out_dir / "metrics.json", metrics)
    return metrics
