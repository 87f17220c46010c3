"""Fitting a scene to one object's captured views, and measuring it on the held-out views.

``fit_scene`` trains on random batches of rays drawn from all training images of a ``transforms.json``
(instant-ngp / nerfstudio format, RGBA images composited over a known background), saves resumable
checkpoints, then ``evaluate_scene`` renders the views of ``transforms_test.json`` and reports PSNR, SSIM
and the depth error against ground-truth depth where the dataset has it.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch

from tnf.errors import TnfError
from tnf.scenes.render import FieldScene, camera_rays

# Defaults per scene kind where one value does not suit both (fit settings of null pick these).
KIND_DEFAULTS: dict[str, dict[str, Any]] = {
    "hashgrid": {"steps": 3000, "batch_rays": 4096, "lr": 1e-2},
    "nerf": {"steps": 30000, "batch_rays": 2048, "lr": 5e-4},
}


@dataclass
class FitSettings:
    """How to fit one scene (the ``fit`` config section)."""

    steps: int | None = None
    """Training steps (ray batches); null: the scene kind's default (hashgrid 3000, nerf 30000)."""
    batch_rays: int | None = None
    """Rays per training batch; null: the scene kind's default (hashgrid 4096, nerf 2048)."""
    lr: float | None = None
    """Adam learning rate at the start; null: the scene kind's default (hashgrid 1e-2, nerf 5e-4)."""
    lr_final_factor: float = 0.05
    """Learning rate at the last step as a fraction of lr (exponential decay)."""
    random_background: bool = True
    """Composite each training ray's RGBA target over a random colour (teaches empty space to be empty)."""
    checkpoint_every: int = 1000
    """Steps between resumable checkpoints (0: none)."""
    eval_views: int | None = None
    """Held-out views to evaluate (null: all of transforms_test.json)."""
    preview_views: int = 4
    """Held-out views shown in preview.png."""
    chunk: int | None = None
    """Rays per rendering chunk during evaluation (bounds memory); null: the scene kind's default."""
    log_every: int = 100
    """Steps between loss records in the training log."""
    carve: bool = True
    """Start the occupancy grid from the visual hull of the training views' alpha masks (skips empty space)."""
    distortion_weight: float = 0.0
    """Weight of the distortion loss (Mip-NeRF 360) that gathers each ray's weights on one surface; scenes
    that report it (hashgrid) only. The colour loss alone leaves the density profile behind an opaque
    surface free, and a spread-out profile biases the expected depth away from the camera."""

    def validate(self) -> None:
        for k in ("steps", "batch_rays"):
            v = getattr(self, k)
            if v is not None and v < 1:
                raise ValueError(f"{k} must be >= 1, got {v}")
        if self.lr is not None and self.lr <= 0:
            raise ValueError(f"lr must be > 0, got {self.lr}")
        if self.distortion_weight < 0:
            raise ValueError(f"distortion_weight must be >= 0, got {self.distortion_weight}")
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


@dataclass
class Views:
    """The frames of one transforms file. All tensors on the CPU."""

    rgba: torch.Tensor  # [N, H, W, 4] float in [0, 1]
    c2w: torch.Tensor  # [N, 4, 4] camera-to-world, OpenGL, metres
    intrinsics: torch.Tensor  # [N, 4] (fx, fy, cx, cy) pixels
    depth: torch.Tensor | None  # [N, H, W] z-depth metres, 0 where no object; None when the dataset has none
    width: int
    height: int


def read_views(path: str | os.PathLike[str], limit: int | None = None) -> Views:
    """The first ``limit`` (default all) frames of a ``transforms.json``-style file (``load_transforms``)."""
    from tnf.capture import load_transforms

    images, c2w, intr, w, h, depth = load_transforms(path)
    n = min(limit, len(images)) if limit else len(images)
    return Views(
        rgba=torch.from_numpy(images[:n]).float() / 255.0,
        c2w=torch.from_numpy(np.asarray(c2w[:n])).float(),
        intrinsics=torch.tensor([intr] * n, dtype=torch.float32),
        depth=torch.from_numpy(depth[:n]) if depth is not None else None,
        width=int(w),
        height=int(h),
    )


def bound_from_cameras(views: Views) -> float:
    """Half-size (metres) of a cube around the origin that holds the object, from the camera setup.

    The object is framed by every camera, so it lies within the nearest camera's view cone; the cube's
    half-size is that camera's distance to the origin times the tangent of its narrowest half field of view.
    """
    dist = views.c2w[:, :3, 3].norm(dim=-1)
    fx, fy = views.intrinsics[:, 0], views.intrinsics[:, 1]
    half = torch.minimum(torch.atan(0.5 * views.width / fx), torch.atan(0.5 * views.height / fy))
    b = (dist * torch.tan(half)).min()
    return float(b)


def object_size(views: Views) -> float | None:
    """Largest extent (metres) of the axis-aligned box around the ground-truth depth points; None without depth."""
    if views.depth is None:
        return None
    pts = []
    for k in range(views.rgba.shape[0]):
        o, d, z = camera_rays(views.c2w[k : k + 1], views.intrinsics[k], views.width, views.height)
        zk = views.depth[k]
        m = zk > 0
        if m.any():
            dist = zk[m] / z[0][m]
            pts.append(o[0][m] + dist.unsqueeze(-1) * d[0][m])
    if not pts:
        return None
    p = torch.cat(pts)
    return float((p.amax(0) - p.amin(0)).max())


def composite(rgba: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """RGB [..., 3] of RGBA [..., 4] over ``background`` ([3] or [..., 3])."""
    a = rgba[..., 3:4]
    return rgba[..., :3] * a + background * (1.0 - a)


def build_scene(spec: dict[str, Any], views: Views) -> FieldScene:
    """Build a scene from ``{"name": kind, **config}``; a null ``bound`` comes from the cameras."""
    from tnf.registry import SCENES, split_spec

    name, params = split_spec(spec, "scene")
    if params.get("bound") is None:
        params["bound"] = bound_from_cameras(views)
    scene = SCENES.build({"name": name, **params})
    if not isinstance(scene, FieldScene):
        raise TnfError(f"scene {name!r} cannot be fitted (it is not a learned field)")
    return scene


def fit_scene(
    scene: FieldScene,
    views: Views,
    settings: FitSettings,
    kind: str,
    device: str = "cpu",
    resume_path: str | os.PathLike[str] | None = None,
    on_step: Callable[[int, float], None] | None = None,
    seed: int = 0,
) -> dict[str, Any]:
    """Train ``scene`` on ``views`` in place; returns ``{"steps", "train_seconds", "final_loss", "log"}``.

    ``resume_path``: a checkpoint file written every ``checkpoint_every`` steps; when it exists, training
    resumes from it (the scene, optimizer and step). It is removed when training completes.
    ``on_step(step, loss)`` is called after every step (progress bars).
    """
    s = settings.resolved(kind)
    assert s.steps is not None and s.batch_rays is not None and s.lr is not None
    scene.to(device).train()
    gen = torch.Generator(device="cpu").manual_seed(seed)
    # All training rays and their RGBA targets, kept on the device: random batches are one gather.
    o, d, _ = camera_rays(views.c2w, views.intrinsics, views.width, views.height)
    o, d = o.reshape(-1, 3).to(device), d.reshape(-1, 3).to(device)
    target = views.rgba.reshape(-1, 4).to(device)
    M = o.shape[0]
    groups = (
        cast(Any, scene).param_groups(s.lr)
        if hasattr(scene, "param_groups")
        else [{"params": list(scene.parameters())}]
    )
    opt = torch.optim.Adam(groups, lr=s.lr, betas=(0.9, 0.99), eps=1e-15)
    gamma = s.lr_final_factor ** (1.0 / max(s.steps, 1))
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma)
    start, log, elapsed = 0, [], 0.0
    resume = Path(resume_path) if resume_path else None
    if resume is not None and resume.is_file():
        ck = torch.load(resume, map_location=device, weights_only=True)
        scene.load_state_dict(ck["scene"])
        opt.load_state_dict(ck["optimizer"])
        sched.load_state_dict(ck["scheduler"])
        start, log, elapsed = int(ck["step"]), list(ck["log"]), float(ck["train_seconds"])
        gen.manual_seed(seed + start)
    t0 = time.perf_counter()
    loss_val = float("nan")
    for step in range(start, s.steps):
        scene.update_occupancy(step)
        idx = torch.randint(0, M, (s.batch_rays,), generator=gen).to(device)
        if s.random_background:
            bg = torch.rand(s.batch_rays, 3, generator=gen).to(device)
        else:
            bg = scene.background.expand(s.batch_rays, 3)
        gt = composite(target[idx], bg)
        out = scene.render_rays(o[idx], d[idx], bg, perturb=True)
        loss = torch.mean((out["rgb"] - gt) ** 2)
        if s.distortion_weight and "distortion" in out:
            loss = loss + s.distortion_weight * out["distortion"].mean()
        if "rgb_coarse" in out:
            loss = loss + torch.mean((out["rgb_coarse"] - gt) ** 2)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        if step % s.log_every == 0 or step == s.steps - 1:
            loss_val = float(loss.detach())
            log.append({"step": step, "loss": loss_val})
        if on_step is not None:
            on_step(step, loss_val)
        if resume is not None and s.checkpoint_every and (step + 1) % s.checkpoint_every == 0 and step + 1 < s.steps:
            _save_resume(resume, scene, opt, sched, step + 1, log, elapsed + time.perf_counter() - t0)
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    elapsed += time.perf_counter() - t0
    if resume is not None and resume.is_file():
        resume.unlink()
    scene.eval()
    return {"steps": s.steps, "train_seconds": elapsed, "final_loss": log[-1]["loss"] if log else None, "log": log}


def _save_resume(path: Path, scene, opt, sched, step: int, log: list, seconds: float) -> None:
    import io

    from tnf.artifacts import write_bytes

    buf = io.BytesIO()
    torch.save(
        {
            "scene": scene.state_dict(),
            "optimizer": opt.state_dict(),
            "scheduler": sched.state_dict(),
            "step": step,
            "log": log,
            "train_seconds": seconds,
        },
        buf,
    )
    write_bytes(path, buf.getvalue())


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
    from tnf.eval.metrics import ssim

    scene.eval()
    dev = scene.background.device
    rgb, depth = [], []
    t0 = time.perf_counter()
    for k in range(views.c2w.shape[0]):
        r = scene.render_rgbd(views.c2w[k : k + 1], views.intrinsics[k], views.width, views.height, chunk)
        rgb.append(r["rgb"].cpu())
        depth.append(r["depth"].cpu())
    if dev.type == "cuda":
        torch.cuda.synchronize()
    seconds = time.perf_counter() - t0
    pred = torch.cat(rgb)
    pdepth = torch.cat(depth)
    gt = composite(views.rgba, scene.background.cpu())
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
        m = views.depth > 0
        if m.any():
            err = (pdepth[m] - views.depth[m]).abs()
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
    from PIL import Image

    from tnf.artifacts import write_json
    from tnf.registry import split_spec
    from tnf.scenes import save_scene

    capture_dir, out_dir = Path(capture_dir), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    kind, _ = split_spec(scene_spec, "scene")
    train = read_views(capture_dir / "transforms.json")
    test_file = capture_dir / "transforms_test.json"
    test = read_views(test_file, settings.eval_views) if test_file.is_file() else None
    torch.manual_seed(seed)
    scene = build_scene(scene_spec, train)
    if settings.carve and hasattr(scene, "carve"):
        # Empty space seen by the cameras is skipped from the first step (visual hull of the RGBA masks).
        cast(Any, scene).carve(train.c2w, train.intrinsics, train.rgba[..., 3])
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    info = fit_scene(scene, train, settings, kind, device, resume_path, on_step, seed)
    size = size_m or object_size(train)
    metrics: dict[str, Any] = {
        "scene": kind,
        "steps": info["steps"],
        "train_seconds": info["train_seconds"],
        "final_loss": info["final_loss"],
        "bound_m": scene.bound,
        "object_size_m": size,
        "train_views": int(train.c2w.shape[0]),
        "resolution": [train.width, train.height],
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
