"""Fitting K hash-grid scenes at once, in one process: every training step renders a batch of rays of each
object and takes ONE forward, backward and optimiser step over all of them (``fit.batch_objects``).

A separate fit (``tnf.scenes.fit.fit_scene``) of a hash grid is a chain of small kernels per step, which
leaves a GPU mostly idle; here the K objects' rays share the kernels. Each object keeps its own parameters,
bound, step size, background and occupancy grid, stacked along a first dimension of size K:

- the hash tables as one table of K * L * T rows (object k's rows start at k * L * T; each sample reads its
  object's rows through ``HashEncoding``'s ``offset``);
- each MLP layer as weights [K, out, in] and biases [K, out], applied with ``torch.baddbmm`` to the samples
  grouped per object in tiles of one object each (``_Tiles``: an object with few samples fills few tiles, so
  the MLPs do not run on padding as wide as the object with the most);
- the occupancy grids as [K, G^3].

What each object sees is what its separate fit sees: the same initial weights (built with the same seed),
the same random draws (a generator per object seeded from ``(seed, step)`` as the separate fit seeds its
device's generator: ray batch, backgrounds, sample offsets, occupancy-refresh points, in the same order),
its own mean loss (the loss is the sum of the objects' means, so each object's gradient is the one it gets
alone), and Adam with the same settings (Adam works element by element). The results differ from separate
fits only by floating-point rounding (batched matrix products sum in another order) and where an object has
no sample in the occupancy grid during a step (module docs of ``fit_batched``).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import io
import logging
import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import torch
from torch import nn

from tnf.artifacts import write_bytes
from tnf.cameras import Views, camera_rays
from tnf.errors import NonFiniteLoss, TnfError
from tnf.runtime import step_seed
from tnf.scenes.encoding import HashEncoding, spherical_harmonics
from tnf.scenes.hashgrid import HashGridScene
from tnf.scenes.render import composite, distortion_loss, ray_aabb, volume_render
from tnf.scenes.settings import FitSettings

log = logging.getLogger(__name__)

#: Version of the group resume checkpoint's ``tnf`` entry; a checkpoint of another version is not resumed from.
#: 2: the fingerprint holds the objects' inputs (``inputs``), which checkpoints of version 1 do not record.
RESUME_FORMAT = 2

#: Points per batched density evaluation of an occupancy refresh, over all objects (bounds its memory).
OCCUPANCY_CHUNK = 1 << 20
#: Points per random draw of an occupancy refresh: the separate fit's chunk, so the draws are the same.
_DRAW_CHUNK = 1 << 18


class BatchedHashGrid(nn.Module):
    """K hash-grid scenes of one config (bounds and backgrounds may differ) as stacked tensors.

    Built from K ``HashGridScene`` objects (their weights, carved hulls and grids copied); ``split_into``
    copies the trained state back into them. Parameters: ``encoding.table`` [K * L * T, F]; per MLP layer
    ``density_w[i]`` / ``color_w[i]`` [K, out, in] and ``density_b[i]`` / ``color_b[i]`` [K, out]. Buffers:
    ``bound`` and ``step_size`` [K] (metres), ``background`` [K, 3], ``occ_density`` [K, G^3] (1/metre),
    ``occupied`` and ``hull`` [K, G^3] (bool, x-major cells).
    """

    bound: torch.Tensor
    step_size: torch.Tensor
    background: torch.Tensor
    occ_density: torch.Tensor
    occupied: torch.Tensor
    hull: torch.Tensor

    def __init__(self, scenes: Sequence[HashGridScene]):
        super().__init__()
        if not scenes:
            raise ValueError("a batched fit needs at least one scene")
        cfg = scenes[0].cfg
        same = {f.name for f in dataclasses.fields(cfg)} - {"bound", "background"}
        for s in scenes[1:]:
            diff = sorted(k for k in same if getattr(s.cfg, k) != getattr(cfg, k))
            if diff:
                raise TnfError(f"scenes fitted together must share their hash-grid config; these differ: {diff}")
        self.cfg = cfg
        self.K = len(scenes)
        enc = scenes[0].encoding
        self.encoding = HashEncoding(
            enc.levels, enc.features, cfg.log2_table_size, cfg.base_resolution, cfg.max_resolution
        )
        self.rows_per_object = enc.levels * enc.table_size
        self.encoding.table = nn.Parameter(torch.cat([s.encoding.table.detach() for s in scenes]))
        self.density_w, self.density_b = _stack_linear([s.density_net for s in scenes])
        self.color_w, self.color_b = _stack_linear([s.color_net for s in scenes])
        #: Per object (Python floats): half-size of the cube (metres) and march step (metres).
        self.bounds = [float(s.bound) for s in scenes]
        self.step_sizes = [float(s.step_size) for s in scenes]
        self.register_buffer("bound", torch.tensor(self.bounds, dtype=torch.float32))
        self.register_buffer("step_size", torch.tensor(self.step_sizes, dtype=torch.float32))
        self.register_buffer("background", torch.stack([s.background.detach().float() for s in scenes]))
        self.register_buffer("occ_density", torch.stack([s.occ_density for s in scenes]))
        self.register_buffer("occupied", torch.stack([s.occupied for s in scenes]))
        self.register_buffer("hull", torch.stack([s.hull for s in scenes]))

    # -- the networks -------------------------------------------------------------------------------
    def _normalise(self, pos: torch.Tensor, bound: torch.Tensor) -> torch.Tensor:
        """Positions [..., 3] (metres) in [0, 1]^3 of their objects' cubes, given each one's ``bound`` [..., 1]."""
        return (pos + bound) / (2.0 * bound)

    def _encode(self, x: torch.Tensor, obj: torch.Tensor) -> torch.Tensor:
        """Hash features [P, L * F] of normalised positions x [P, 3] of objects ``obj`` [P] (int64)."""
        return self.encoding(x, offset=obj * self.rows_per_object)

    def _density_head(self, feats: torch.Tensor, tile_obj: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Density [M, T] (1/metre) and geometry features [M, T, geo] from hash features [M, T, L * F] laid out
        in M tiles, tile m of object ``tile_obj[m]``."""
        h = _batched_mlp(self.density_w, self.density_b, feats, tile_obj)
        # As HashGridScene.density: exp activation, clamped, biased down.
        return torch.exp((h[..., 0] - 1.0).clamp(max=15.0)), h[..., 1:]

    def field(self, x: torch.Tensor, dirs: torch.Tensor, obj: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Density [P] and colour [P, 3] in [0, 1] at normalised positions x [P, 3] seen along unit ``dirs``
        [P, 3], sample p belonging to object ``obj[p]``; ``obj`` must be non-decreasing (samples grouped per
        object). The MLPs run on the samples laid out in tiles of one object each (``_Tiles``)."""
        tiles = _Tiles(obj, self.K)
        sigma, geo = self._density_head(tiles.pack(self._encode(x, obj)), tiles.obj)
        color_in = torch.cat([tiles.pack(spherical_harmonics(dirs)), geo], dim=-1)
        rgb = _batched_mlp(self.color_w, self.color_b, color_in, tiles.obj)
        return tiles.unpack(sigma), torch.sigmoid(tiles.unpack(rgb))

    def density(self, x: torch.Tensor, obj: torch.Tensor) -> torch.Tensor:
        """Density [P] (1/metre) at normalised positions x [P, 3] of objects ``obj`` [P] (non-decreasing)."""
        tiles = _Tiles(obj, self.K)
        return tiles.unpack(self._density_head(tiles.pack(self._encode(x, obj)), tiles.obj)[0])

    # -- rendering with gradients -------------------------------------------------------------------
    def render_rays(
        self, origins: torch.Tensor, dirs: torch.Tensor, background: torch.Tensor, offset: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """Render K * B rays, the B rays of object k in rows k * B to (k + 1) * B: origins [R, 3] (metres), unit
        dirs [R, 3], background [R, 3], sample offsets [R, 1] in [0, 1) (steps). As
        ``HashGridScene.render_rays`` with gradients: every sample in the cube that the object's occupancy
        grid keeps is rendered. Returns rgb [R, 3], depth [R] (metres), opacity [R] and distortion [R] (in
        units of the object's cube)."""
        R, N, G = origins.shape[0], self.cfg.samples_per_ray, self.cfg.occupancy_resolution
        dev = origins.device
        ray_obj = torch.arange(self.K, device=dev).repeat_interleave(R // self.K)  # [R]
        bound = self.bound[ray_obj].unsqueeze(1)  # [R, 1]
        dt = self.step_size[ray_obj].unsqueeze(1)  # [R, 1]
        near, far = ray_aabb(origins, dirs, -bound, bound)
        t = near.unsqueeze(1) + (torch.arange(N, device=dev) + offset) * dt  # [R, N]
        valid = t < far.unsqueeze(1)
        ri, si = valid.nonzero(as_tuple=True)
        obj = ray_obj[ri]
        pos = origins[ri] + t[ri, si].unsqueeze(-1) * dirs[ri]
        x = self._normalise(pos, bound[ri])
        c = (x * G).long().clamp(0, G - 1)
        cell = (c[..., 0] * G + c[..., 1]) * G + c[..., 2]
        keep = self.occupied.view(-1)[obj * G**3 + cell]
        ri, si, x, obj = ri[keep], si[keep], x[keep], obj[keep]
        sigma = origins.new_zeros(R, N)
        rgb = origins.new_zeros(R, N, 3)
        if ri.numel() > 0:
            s, col = self.field(x, dirs[ri], obj)
            sigma = sigma.index_put((ri, si), s)
            rgb = rgb.index_put((ri, si), col)
        delta = valid.float() * dt
        out = volume_render(sigma, rgb, t, delta, background, start=t - offset * dt)
        dist = distortion_loss(out["weights"], t, delta) / (2.0 * bound[:, 0])
        return {"rgb": out["rgb"], "depth": out["depth"], "opacity": out["opacity"], "distortion": dist}

    # -- occupancy grids ----------------------------------------------------------------------------
    @torch.no_grad()
    def update_occupancy(self, step: int, generators: Sequence[torch.Generator]) -> None:
        """Refresh every object's occupancy grid as ``HashGridScene.update_occupancy`` does, object k's random
        points drawn from ``generators[k]``; every ``occupancy_update_every`` steps only."""
        cfg = self.cfg
        if step % cfg.occupancy_update_every != 0:
            return
        K, G = self.K, cfg.occupancy_resolution
        dev = self.occ_density.device
        ar = torch.arange(G, device=dev)
        cells = torch.stack(torch.meshgrid(ar, ar, ar, indexing="ij"), dim=-1).reshape(-1, 3).float()
        # Per object: its hull cells and a random point in each (drawn in the separate fit's chunks).
        xs, index = [], []
        for k, (g, b) in enumerate(zip(generators, self.bounds, strict=True)):
            sel = self.hull[k].nonzero(as_tuple=True)[0]
            c = cells[sel]
            r = [
                torch.rand(c[i : i + _DRAW_CHUNK].shape, device=dev, generator=g) for i in range(0, len(c), _DRAW_CHUNK)
            ]
            pos = ((c + torch.cat(r)) / G) * (2 * b) - b if r else c
            xs.append((pos + b) / (2.0 * b))
            index.append(sel + k * G**3)
        x, flat = torch.cat(xs), torch.cat(index)
        obj = flat // G**3  # non-decreasing: the objects' points one after the other
        full = torch.zeros(K * G**3, device=dev)
        for i in range(0, len(x), OCCUPANCY_CHUNK):
            full[flat[i : i + OCCUPANCY_CHUNK]] = self.density(x[i : i + OCCUPANCY_CHUNK], obj[i : i + OCCUPANCY_CHUNK])
        self.occ_density.copy_(torch.maximum(self.occ_density * cfg.occupancy_decay, full.view(K, -1)))
        if step < cfg.occupancy_warmup:
            self.occupied.copy_(self.hull)
            return
        from_step = torch.tensor(
            [-math.log(1.0 - cfg.occupancy_threshold) / dt for dt in self.step_sizes], device=dev, dtype=torch.float32
        )
        cells_in = self.hull.sum(1)
        mean = torch.where(cells_in > 0, (self.occ_density * self.hull).sum(1) / cells_in.clamp_min(1), 0.0)
        threshold = torch.minimum(from_step, mean)
        self.occupied.copy_((self.occ_density > threshold.unsqueeze(1)) & self.hull)

    # -- optimiser groups and the way back ----------------------------------------------------------
    def param_groups(self, lr: float) -> list[dict]:
        """Optimiser groups as ``HashGridScene.param_groups``: the hash tables without weight decay, the MLPs
        with a little."""
        mlps = [*self.density_w, *self.density_b, *self.color_w, *self.color_b]
        return [
            {"params": [self.encoding.table], "lr": lr, "weight_decay": 0.0},
            {"params": mlps, "lr": lr, "weight_decay": 1e-6},
        ]

    @torch.no_grad()
    def split_into(self, scenes: Sequence[HashGridScene]) -> None:
        """Copy object k's trained table, MLPs and grids into ``scenes[k]`` (the scenes it was built from)."""
        table = self.encoding.table.view(self.K, self.rows_per_object, -1)
        for k, s in enumerate(scenes):
            s.encoding.table.copy_(table[k])
            for net, ws, bs in (
                (s.density_net, self.density_w, self.density_b),
                (s.color_net, self.color_w, self.color_b),
            ):
                for layer, w, b in zip(_linears(net), ws, bs, strict=True):
                    layer.weight.copy_(w[k])
                    layer.bias.copy_(b[k])
            s.occ_density.copy_(self.occ_density[k])
            s.occupied.copy_(self.occupied[k])
            s.hull.copy_(self.hull[k])


def _linears(net: nn.Module) -> list[nn.Linear]:
    return [m for m in net.modules() if isinstance(m, nn.Linear)]


def _stack_linear(nets: Sequence[nn.Module]) -> tuple[nn.ParameterList, nn.ParameterList]:
    """Weights [K, out, in] and biases [K, out] of each linear layer of K MLPs of one shape."""
    layers = [_linears(n) for n in nets]
    ws = nn.ParameterList([torch.stack([ls[i].weight.detach() for ls in layers]) for i in range(len(layers[0]))])
    bs = nn.ParameterList([torch.stack([ls[i].bias.detach() for ls in layers]) for i in range(len(layers[0]))])
    return ws, bs


def _batched_mlp(ws: nn.ParameterList, bs: nn.ParameterList, x: torch.Tensor, tile_obj: torch.Tensor) -> torch.Tensor:
    """K MLPs (``tnf.scenes.encoding.mlp``: linear layers with ReLU between) on M tiles x [M, T, in] -> [M, T,
    out], tile m through the MLP of object ``tile_obj[m]``."""
    last = len(ws) - 1
    for i, (w, b) in enumerate(zip(ws, bs, strict=True)):
        x = torch.baddbmm(b[tile_obj].unsqueeze(1), x, w[tile_obj].transpose(1, 2))
        if i < last:
            x = torch.relu(x)
    return x


class _Tiles:
    """P samples grouped per object (``obj`` [P] non-decreasing, K objects) laid out in M tiles of T rows, each
    tile holding samples of one object only (the last tile of an object padded with zeros), so that batched
    matrix products run on about P rows rather than K times the most samples of one object. T is a power of two,
    P / 8K rounded down and at least 256: padding adds fewer than K * T rows, at most an eighth of P once P
    reaches 2048 K."""

    def __init__(self, obj: torch.Tensor, K: int):
        P = obj.shape[0]
        self.size = max(256, 1 << max(0, (P // (8 * K)).bit_length() - 1))
        counts = torch.bincount(obj, minlength=K)
        per_object = (counts + self.size - 1) // self.size
        self.count = int(per_object.sum())
        first_row = torch.cumsum(counts, 0) - counts
        first_tile = torch.cumsum(per_object, 0) - per_object
        #: Row of each sample in the tiles' [M * T] rows, and the object of each tile [M].
        self.slot = first_tile[obj] * self.size + torch.arange(P, device=obj.device) - first_row[obj]
        self.obj = torch.repeat_interleave(torch.arange(K, device=obj.device), per_object, output_size=self.count)

    def pack(self, values: torch.Tensor) -> torch.Tensor:
        """Per-sample values [P, C] as tiles [M, T, C]."""
        rows = values.new_zeros(self.count * self.size, values.shape[1]).index_put((self.slot,), values)
        return rows.view(self.count, self.size, -1)

    def unpack(self, tiles: torch.Tensor) -> torch.Tensor:
        """Tiles [M, T, ...] back to per-sample values [P, ...]."""
        return tiles.reshape(self.count * self.size, *tiles.shape[2:])[self.slot]


class _Rays:
    """Every training ray of K objects, concatenated on the device: ``origins``, ``directions`` [M, 3]
    (metres, unit), ``targets`` [M, 4] (RGBA in [0, 1]); object k's rays start at row ``start[k]``, and it has
    ``count[k]``."""

    def __init__(self, views: Sequence[Views], device: torch.device):
        o, d, t = [], [], []
        for v in views:
            ok, dk, _ = camera_rays(*v.cameras(), v.width, v.height)
            o.append(ok.reshape(-1, 3))
            d.append(dk.reshape(-1, 3))
            t.append(v.rgba().reshape(-1, 4))
        self.count = [int(x.shape[0]) for x in o]
        self.start = [sum(self.count[:k]) for k in range(len(o))]
        self.origins = torch.cat(o).to(device)
        self.directions = torch.cat(d).to(device)
        self.targets = torch.cat(t).to(device)


def fit_batched(
    scenes: Sequence[HashGridScene],
    views: Sequence[Views],
    settings: FitSettings,
    device: str = "cpu",
    resume_path: str | os.PathLike[str] | None = None,
    on_step: Callable[[int, float], None] | None = None,
    seed: int = 0,
    names: Sequence[str] | None = None,
    inputs: Sequence[Any] | None = None,
) -> list[dict[str, Any]]:
    """Train K hash-grid ``scenes`` on their ``views`` together, in place; returns per object what
    ``fit_scene`` returns (``steps``, ``train_seconds``: the group's wall time, ``final_loss``, ``log``) and
    ``checkpoint_seconds``, the part of ``train_seconds`` that the loop waited for resume checkpoints in this
    call (their copy to the host; a background thread writes them).

    Each step draws ``batch_rays`` rays of every object and takes one Adam step over all of them; the
    objects' learning-rate schedule, loss (colour, distortion), random backgrounds and occupancy refreshes
    are those of ``fit_scene``. ``settings`` must be resolved (``FitSettings.resolved``). ``resume_path``: a
    checkpoint of the whole group written atomically every ``checkpoint_every`` steps; a checkpoint of the
    same group, inputs and settings is resumed from and the fit ends exactly as an uninterrupted one; another
    is removed, with a warning that says why; removed at the end. ``inputs``: what each object's fit is made
    from (``tnf.scenes.fit.fit_inputs``), which the checkpoint must match; None checks only the settings, ray
    counts, bounds and tensor shapes. ``on_step(step, loss)``: after every step, with the mean over objects of
    the last recorded losses. ``names``: the objects' names, for messages. A NaN or infinite loss raises
    ``NonFiniteLoss`` naming the object and step. The scenes end on ``device`` in eval mode.

    One difference from separate fits: an object none of whose samples lies in an occupied cell during a
    step gets zero gradients for its MLPs there, which Adam applies (its momentum moves them), where its
    separate fit would skip the step for them. It can happen only in a step in which all of an object's
    rays miss its occupied cells.
    """
    s = settings
    assert s.steps is not None and s.batch_rays is not None and s.lr is not None
    K, B, steps = len(scenes), s.batch_rays, s.steps
    names = list(names) if names is not None else [str(k) for k in range(K)]
    dev = torch.device(device)
    model = BatchedHashGrid(scenes).to(dev).train()
    model.encoding.train_kernel = s.train_kernel
    rays = _Rays(views, dev)
    opt = torch.optim.Adam(model.param_groups(s.lr), lr=s.lr, betas=(0.9, 0.99), eps=1e-15)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, s.lr_final_factor ** (1.0 / max(steps, 1)))
    fingerprint = _fingerprint(s, seed, rays.count, model, inputs)
    logs: list[list[dict[str, Any]]] = [[] for _ in range(K)]
    first, earlier_seconds = 0, 0.0
    resume = Path(resume_path) if resume_path is not None else None
    if resume is not None and resume.is_file():
        ckpt, why = _read_resume(resume, fingerprint, names)
        if ckpt is None:
            log.warning("not resuming from %s (%s): the batched fit starts afresh", resume, why)
            resume.unlink()
        else:
            model.load_state_dict(ckpt["model"])
            opt.load_state_dict(ckpt["optimizer"])
            sched.load_state_dict(ckpt["scheduler"])
            meta = ckpt["tnf"]
            first, earlier_seconds, logs = int(meta["step"]), float(meta["train_seconds"]), meta["log"]
    generators = [torch.Generator(device=dev) for _ in range(K)]
    distortion_from = int(round(s.distortion_start * steps))
    recent = torch.empty(s.log_every, K, device=dev)  # per-object losses since the last read
    recent_from = first
    last_loss = [float(x[-1]["loss"]) if x else float("nan") for x in logs]
    checkpoint_seconds = 0.0  # the loop's waits for checkpoints: copying them to the host, not writing them
    writer = _ResumeWriter()
    started = time.perf_counter()
    try:
        for step in range(first, steps):
            for g in generators:
                g.manual_seed(step_seed(seed, step))
            model.update_occupancy(step, generators)
            # Object by object, its draws in the order of its separate fit: ray batch, backgrounds, offsets.
            idx, bg, off = [], [], []
            for k, g in enumerate(generators):
                idx.append(torch.randint(0, rays.count[k], (B,), device=dev, generator=g) + rays.start[k])
                bg.append(
                    torch.rand(B, 3, device=dev, generator=g)
                    if s.random_background
                    else model.background[k].expand(B, 3)
                )
                off.append(torch.rand(B, 1, device=dev, generator=g))
            sel, background = torch.cat(idx), torch.cat(bg)
            gt = composite(rays.targets[sel], background)
            out = model.render_rays(rays.origins[sel], rays.directions[sel], background, torch.cat(off))
            per_object = ((out["rgb"] - gt) ** 2).view(K, -1).mean(1)
            if s.distortion_weight and step >= distortion_from:
                per_object = per_object + s.distortion_weight * out["distortion"].view(K, B).mean(1)
            opt.zero_grad(set_to_none=True)
            per_object.sum().backward()
            opt.step()
            sched.step()
            recent[step - recent_from] = per_object.detach()
            last = step == steps - 1
            log_now = step % s.log_every == 0 or last
            every = s.checkpoint_every
            save_now = resume is not None and every > 0 and (step + 1) % every == 0 and not last
            if log_now or save_now:
                losses = _read_losses(recent[: step - recent_from + 1], recent_from, names, resume, writer.wait)
                recent_from = step + 1
                if log_now:
                    last_loss = losses
                    for k in range(K):
                        logs[k].append({"step": step, "loss": losses[k]})
            if save_now:
                assert resume is not None
                seconds = earlier_seconds + time.perf_counter() - started
                t_save = time.perf_counter()
                writer.write(resume, _resume_state(fingerprint, step + 1, seconds, logs, model, opt, sched))
                checkpoint_seconds += time.perf_counter() - t_save
            if on_step is not None:
                on_step(step, sum(last_loss) / K)
    except BaseException:
        writer.wait(reraise=False)
        raise
    writer.wait()
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)
    seconds = earlier_seconds + time.perf_counter() - started
    for scene in scenes:
        scene.to(dev)
    model.split_into(scenes)
    for scene in scenes:
        scene.eval()
    if resume is not None:
        resume.unlink(missing_ok=True)
    return [
        {
            "steps": steps,
            "train_seconds": seconds,
            "checkpoint_seconds": checkpoint_seconds,
            "final_loss": logs[k][-1]["loss"] if logs[k] else None,
            "log": logs[k],
        }
        for k in range(K)
    ]


def _read_losses(
    recent: torch.Tensor,
    recent_from: int,
    names: Sequence[str],
    resume: Path | None,
    settle: Callable[[], None] = lambda: None,
) -> list[float]:
    """The per-object losses of the last step in ``recent`` [steps, K] (steps from ``recent_from``);
    ``NonFiniteLoss`` names the first object and step with a NaN or infinite loss, and the checkpoint left
    once ``settle()`` (a checkpoint write in progress) returns."""
    r = recent.cpu()
    bad = (~torch.isfinite(r)).nonzero()
    if bad.numel():
        settle()
        step, k = recent_from + int(bad[0, 0]), int(bad[0, 1])
        note = (
            f"the last good checkpoint is {resume}"
            if resume is not None and resume.is_file()
            else "no checkpoint was saved yet"
        )
        raise NonFiniteLoss(
            f"non-finite scene fitting loss (NaN or Inf) of object {names[k]!r} at step {step} of a batched fit; "
            f"the fit stopped ({note}); lower fit.lr or check the capture's images"
        )
    return [float(x) for x in r[-1]]


def _fingerprint(
    s: FitSettings, seed: int, counts: Sequence[int], model: BatchedHashGrid, inputs: Sequence[Any] | None = None
) -> dict[str, Any]:
    """What a group's resume checkpoint must match: each object's inputs (``tnf.scenes.fit.fit_inputs``: the
    identity of its captured images and its scene's settings), the training settings, the seed, each object's
    ray count and bound, and the shapes of the stacked tensors. Settings that do not change the fitted scenes
    (``checkpoint_every``, ``log_every``, ``chunk``, the evaluation's) are left out."""
    return {
        "steps": s.steps,
        "batch_rays": s.batch_rays,
        "lr": s.lr,
        "lr_final_factor": s.lr_final_factor,
        "random_background": s.random_background,
        "distortion_weight": s.distortion_weight,
        "distortion_start": s.distortion_start,
        **({"train_kernel": True} if s.train_kernel else {}),
        "seed": seed,
        "inputs": list(inputs) if inputs is not None else None,
        "rays": list(counts),
        "bounds": list(model.bounds),
        "shapes": {k: list(v.shape) for k, v in model.state_dict().items()},
    }


def _resume_state(
    fingerprint: dict[str, Any],
    step: int,
    seconds: float,
    logs: list[list[dict[str, Any]]],
    model: BatchedHashGrid,
    opt: torch.optim.Optimizer,
    sched: Any,
) -> dict[str, Any]:
    """The group's checkpoint, a copy on the host that the training steps after it do not change: the next
    step to take, the model, optimiser, scheduler, logs."""
    meta = {"format": RESUME_FORMAT, "kind": "scene_fit_batched", "fit": fingerprint, "step": step}
    meta.update({"train_seconds": seconds, "log": copy.deepcopy(logs)})
    state = {"model": model.state_dict(), "optimizer": opt.state_dict(), "scheduler": sched.state_dict()}
    return {"tnf": meta, **_host_copy(state)}


def _host_copy(obj: Any) -> Any:
    """``obj`` with every tensor in it (in dicts, lists and tuples) copied to host memory."""
    if isinstance(obj, torch.Tensor):
        return obj.detach().to("cpu", copy=True)
    if isinstance(obj, dict):
        return {k: _host_copy(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(_host_copy(v) for v in obj)
    return copy.deepcopy(obj)


def _write_resume(path: Path, state: dict[str, Any]) -> None:
    """Write a checkpoint of ``_resume_state`` atomically."""
    buf = io.BytesIO()
    torch.save(state, buf)
    write_bytes(path, buf.getbuffer())


class _ResumeWriter:
    """Writes resume checkpoints atomically in a background thread, one at a time, so that training goes on
    while the checkpoint is serialised, written and flushed to disk. ``wait`` returns once the last write is
    done and raises its error, if any (a full disk: ``tnf.artifacts.DiskFull``)."""

    def __init__(self) -> None:
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def write(self, path: Path, state: dict[str, Any]) -> None:
        """Write ``state`` (``_resume_state``) to ``path`` once the previous write is done."""
        self.wait()

        def run() -> None:
            try:
                _write_resume(path, state)
            except BaseException as e:  # raised in the training thread by wait()
                self._error = e

        self._thread = threading.Thread(target=run, name="tnf-resume-writer", daemon=True)
        self._thread.start()

    def wait(self, reraise: bool = True) -> None:
        """Wait for the write in progress; raise its error unless ``reraise`` is false."""
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        error, self._error = self._error, None
        if error is not None and reraise:
            raise error


def _read_resume(path: Path, fingerprint: dict[str, Any], names: Sequence[str]) -> tuple[dict[str, Any] | None, str]:
    """The group checkpoint at ``path`` if it can be resumed from, else None and why not (``names``: the objects'
    names, to say whose inputs changed)."""
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises several types for files that are not checkpoints
        return None, f"unreadable ({str(e).splitlines()[0][:200]})"
    meta = ckpt.get("tnf") if isinstance(ckpt, dict) else None
    if not isinstance(meta, dict) or meta.get("kind") != "scene_fit_batched" or meta.get("format") != RESUME_FORMAT:
        return None, "written by another tnf version"
    fit = meta.get("fit")
    if fit != fingerprint:
        return None, _other_inputs(fit, fingerprint, names) or "written by a fit with other settings or objects"
    return ckpt, ""


def _other_inputs(old: Any, new: dict[str, Any], names: Sequence[str]) -> str | None:
    """Why a group checkpoint of fingerprint ``old`` was made from other inputs than a fit of fingerprint
    ``new`` of the objects ``names``; None when the inputs are the same, unknown or of another number of
    objects."""
    from tnf.scenes.system import other_inputs

    a = old.get("inputs") if isinstance(old, dict) else None
    b = new.get("inputs")
    if not isinstance(a, list) or not isinstance(b, list) or len(a) != len(b) or len(b) != len(names):
        return None
    why: dict[str, list[str]] = {}
    for name, x, y in zip(names, a, b, strict=True):
        reason = other_inputs({"inputs": x}, {"inputs": y})
        if reason is not None:
            why.setdefault(reason, []).append(name)
    return "; ".join(f"{reason} of {', '.join(objs)}" for reason, objs in why.items()) or None


def group_resume_name(names: Sequence[str]) -> str:
    """File name of a group's resume checkpoint: the first object, the group's size and a hash of its names."""
    digest = hashlib.sha256("\n".join(names).encode()).hexdigest()[:10]
    return f"{names[0]}+{len(names) - 1}-{digest}.pt"


def fit_objects(
    scene_specs: Sequence[dict[str, Any]],
    capture_dirs: Sequence[str | os.PathLike[str]],
    out_dirs: Sequence[str | os.PathLike[str]],
    settings: FitSettings,
    device: str = "cpu",
    resume_path: str | os.PathLike[str] | None = None,
    on_step: Callable[[int, float], None] | None = None,
    seed: int = 0,
    sizes_m: Sequence[float | None] | None = None,
    names: Sequence[str] | None = None,
) -> list[dict[str, Any]]:
    """``tnf.scenes.fit.fit_object`` for K hash-grid objects fitted together (``fit_batched``): each object's
    scene is built and carved as there (same seed), and written as there into its ``out_dirs[k]``
    (``scene.pt``, ``metrics.json``, ``preview.png``). Returns each object's metrics; ``train_seconds`` is
    the object's share of the group's training time (the group's time / K), ``group_train_seconds`` the
    whole, ``batch_objects`` K."""
    from tnf.cameras import read_views
    from tnf.registry import split_spec
    from tnf.scenes.fit import build_scene, fit_inputs, write_fit

    K = len(scene_specs)
    kinds = {split_spec(spec, "scene")[0] for spec in scene_specs}
    if kinds != {"hashgrid"}:
        raise TnfError(f"fit.batch_objects > 1 fits hashgrid scenes only, not {sorted(kinds)}; set fit.batch_objects=1")
    s = settings.resolved("hashgrid")
    t_setup = time.perf_counter()
    # Reading the views and carving are per object and need no random numbers: threads (image decoding, scipy
    # and torch release the GIL), as many as the cores hold beside torch's own threads; building draws each
    # scene's initial weights from the seed, one at a time.
    workers = max(1, min(K, (os.cpu_count() or 1) // max(1, torch.get_num_threads())))
    with ThreadPoolExecutor(max_workers=workers) as pool:
        trains = list(pool.map(lambda c: read_views(Path(c) / "transforms.json"), capture_dirs))
        scenes: list[HashGridScene] = []
        for spec, train in zip(scene_specs, trains, strict=True):
            torch.manual_seed(seed)
            scene = build_scene(spec, train)
            assert isinstance(scene, HashGridScene)
            scenes.append(scene)
        if s.carve:
            list(pool.map(lambda k: scenes[k].carve(*trains[k].cameras(), trains[k].rgba()[..., 3]), range(K)))
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    setup_seconds = time.perf_counter() - t_setup
    inputs = [fit_inputs(spec, c) for spec, c in zip(scene_specs, capture_dirs, strict=True)]
    infos = fit_batched(scenes, trains, s, device, resume_path, on_step, seed, names, inputs)
    t_write = time.perf_counter()
    out = []
    for k in range(K):
        info = dict(infos[k], train_seconds=infos[k]["train_seconds"] / K)
        extra = {
            "group_train_seconds": infos[k]["train_seconds"],
            "group_checkpoint_seconds": infos[k]["checkpoint_seconds"],
            "group_setup_seconds": setup_seconds,
            "batch_objects": K,
        }
        size = sizes_m[k] if sizes_m is not None else None
        out.append(
            write_fit(scenes[k], "hashgrid", trains[k], capture_dirs[k], out_dirs[k], s, info, device, size, extra)
        )
        scenes[k].cpu()  # the fitted objects' device memory is not needed any more
    log.info(
        "batched fit of %d objects: %.1f s reading and carving, %.1f s training (%.1f s of it copying checkpoints), "
        "%.1f s evaluating and writing",
        K,
        setup_seconds,
        infos[0]["train_seconds"],
        infos[0]["checkpoint_seconds"],
        time.perf_counter() - t_write,
    )
    return out
