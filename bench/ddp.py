"""Steady-state training speed under DDP: pairs per second on 1, 2, 4 ... devices at the same per-device batch.

    python bench/ddp.py --devices 1,2,4                  # tn_cgan, batch 64 per device, bf16, as trainer=ddp runs
    python bench/ddp.py --devices 1,2 --graph find-unused  # DDP searching for unused parameters every step
    python bench/ddp.py --devices 2 --comm-hook bf16        # gradients all-reduced in bf16 (half the bytes)
    python bench/ddp.py --devices 2 --profile               # rank 0's 20 busiest operators over 20 batches
    python bench/ddp.py --devices 1,2,4 --compile default   # networks through torch.compile (or reduce-overhead)
    python bench/ddp.py --accelerator cpu --devices 1,2 --batch 4 --steps 6 --warmup 2 --precision 32-true

Each device count runs in its own process: tnf's ``GeneratorSystem`` in a Lightning ``Trainer`` with
``DDPStrategy`` (spawned processes, as ``trainer=ddp``), no validation, no logger, no checkpoints. Every step
trains on one random batch already on the device (``bench/generators.py``'s ``batch_on``), so the figure is the
model's step and DDP's gradient sync only: no loader, no start-up, no validation. The clock runs from batch
``--warmup`` to step ``--warmup + --steps`` on rank 0, after a device synchronisation at both ends. Pairs per
second = steps x batch x devices / seconds. The last column is the speed-up over the first device count.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from typing import Any

import lightning as L
import torch
from generators import batch_on  # bench/generators.py
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.strategies import DDPStrategy

from tnf.generators.system import GeneratorSystem
from tnf.generators.training import ddp_strategy


class Steps(torch.utils.data.Dataset):
    """``n`` placeholder items: the batches themselves are made on the device (``SyntheticSystem``)."""

    def __init__(self, n: int):
        self.n = n

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> torch.Tensor:
        return torch.zeros(())


class SyntheticSystem(GeneratorSystem):
    """``GeneratorSystem`` whose every training batch is one random batch made once on its device."""

    def __init__(self, *args: Any, batch: int, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.bench_batch = batch
        self._cache: dict[str, torch.Tensor] | None = None

    def on_after_batch_transfer(self, batch: Any, dataloader_idx: int) -> dict[str, torch.Tensor]:
        if self._cache is None:
            self._cache = batch_on(str(self.device), self.bench_batch, channels_last=self.device.type == "cuda")
        return self._cache


class Profile(Callback):
    """Rank 0's operators over ``batches`` training batches from batch ``start``: the busiest by device time
    (CPU time on a CPU), printed as torch.profiler's table."""

    def __init__(self, start: int, batches: int = 20):
        self.start, self.stop = start, start + batches
        self.seen = 0
        self.prof: Any = None

    def on_train_batch_start(self, trainer: Any, pl_module: Any, batch: Any, batch_idx: int) -> None:
        self.seen += 1
        if not trainer.is_global_zero:
            return
        if self.seen - 1 == self.start:
            acts = [torch.profiler.ProfilerActivity.CPU]
            if pl_module.device.type == "cuda":
                acts.append(torch.profiler.ProfilerActivity.CUDA)
            self.prof = torch.profiler.profile(activities=acts)
            self.prof.__enter__()
        elif self.seen - 1 == self.stop and self.prof is not None:
            if pl_module.device.type == "cuda":
                torch.cuda.synchronize(pl_module.device)
            self.prof.__exit__(None, None, None)
            key = "device_time_total" if pl_module.device.type == "cuda" else "cpu_time_total"
            print(self.prof.key_averages().table(sort_by=key, row_limit=20, max_name_column_width=60), flush=True)
            self.prof = None


class Clock(Callback):
    """Wall seconds between the starts of two training batches, each after a device synchronisation."""

    def __init__(self, start: int, stop: int):
        self.start, self.stop = start, stop
        self.t0: float | None = None
        self.seconds: float | None = None
        self.batches = 0

    def on_train_batch_start(self, trainer: Any, pl_module: Any, batch: Any, batch_idx: int) -> None:
        self.batches += 1  # batches, not optimiser steps: a GAN's step is two of those
        if self.batches - 1 not in (self.start, self.stop):
            return
        if pl_module.device.type == "cuda":
            torch.cuda.synchronize(pl_module.device)
        if self.batches - 1 == self.start:
            self.t0 = time.perf_counter()
        elif self.t0 is not None:
            self.seconds = time.perf_counter() - self.t0
            if trainer.is_global_zero:  # printed here: under spawn this process is not the one that started fit
                rate = (self.stop - self.start) * pl_module.bench_batch * trainer.world_size / self.seconds
                print(f"RESULT {rate:.1f}", flush=True)


def run_one(args: argparse.Namespace, devices: int) -> None:
    """Train on ``devices`` devices; rank 0 prints ``RESULT <pairs per second>``."""
    torch.backends.cudnn.benchmark = True
    torch.backends.cuda.matmul.allow_tf32 = True
    torch.backends.cudnn.allow_tf32 = True
    system = SyntheticSystem(
        {"name": args.generator}, epochs=1, decay_epochs=0, batch=args.batch, compile_nets=args.compile
    )
    clock = Clock(args.warmup, args.warmup + args.steps)
    strategy: Any = "auto"
    if devices > 1 and args.graph == "tnf":
        strategy = ddp_strategy("ddp_spawn", fixed_graph=system.generator.fixed_graph())
    elif devices > 1:
        strategy = DDPStrategy(
            find_unused_parameters="find-unused" in args.graph,
            static_graph="static" in args.graph,
            gradient_as_bucket_view=args.bucket_view,
            start_method="spawn",
        )
    if devices > 1 and args.comm_hook == "bf16":
        from torch.distributed.algorithms.ddp_comm_hooks import default_hooks

        strategy._ddp_comm_hook = default_hooks.bf16_compress_hook
    if devices > 1 and args.bucket_mb:
        strategy._ddp_kwargs["bucket_cap_mb"] = args.bucket_mb
    callbacks: list[Any] = [Profile(args.warmup) if args.profile else clock]
    trainer = L.Trainer(
        accelerator=args.accelerator,
        devices=devices,
        strategy=strategy,
        precision=args.precision,
        max_epochs=1,
        limit_val_batches=0,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        callbacks=callbacks,
    )
    loader = torch.utils.data.DataLoader(Steps((args.warmup + args.steps + 2) * devices), batch_size=1)
    trainer.fit(system, loader)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--devices", default="1,2", help="comma-separated device counts, each timed in its own process")
    p.add_argument("--generator", default="tn_cgan")
    p.add_argument("--batch", type=int, default=64, help="pairs per device per step")
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--warmup", type=int, default=30)
    p.add_argument("--accelerator", default="gpu")
    p.add_argument("--precision", default="bf16-mixed")
    p.add_argument(
        "--graph",
        choices=["tnf", "find-unused", "static", "static+find-unused", "plain"],
        default="tnf",
        help="tnf: as trainer=ddp runs (tnf.generators.training.ddp_strategy); the others set DDP's "
        "find_unused_parameters and static_graph as named (plain: neither)",
    )
    p.add_argument("--bucket-view", action="store_true", help="gradient_as_bucket_view=True (not with tnf)")
    p.add_argument(
        "--comm-hook", choices=["none", "bf16"], default="none", help="bf16: DDP all-reduces gradients in bf16"
    )
    p.add_argument("--bucket-mb", type=int, default=0, help="DDP's bucket_cap_mb (0: its default, 25)")
    p.add_argument("--compile", default="", help="torch.compile mode for the networks: default, reduce-overhead, ...")
    p.add_argument("--profile", action="store_true", help="print rank 0's busiest operators instead of timing")
    p.add_argument("--json", help="also write the figures here")
    p.add_argument("--one", type=int, help=argparse.SUPPRESS)  # internal: time this device count and print it
    args = p.parse_args()
    if args.one is not None:
        run_one(args, args.one)
        return
    counts = [int(c) for c in args.devices.split(",")]
    rows = []
    for n in counts:
        cmd = [sys.executable, __file__, *sys.argv[1:], "--one", str(n)]
        done = subprocess.run(cmd, capture_output=True, text=True)
        if args.profile:
            print(f"{n} device(s):", done.stdout[-12000:], done.stderr[-3000:] if done.returncode else "")
            continue
        found = [ln for ln in done.stdout.splitlines() if ln.startswith("RESULT ")]
        if done.returncode != 0 or not found:
            print(done.stdout[-2000:], done.stderr[-4000:], file=sys.stderr)
            raise SystemExit(f"{n} device(s): the run failed (exit {done.returncode})")
        rows.append((n, float(found[-1].split()[1])))
    if not rows:
        return
    name = torch.cuda.get_device_name(0) if args.accelerator == "gpu" and torch.cuda.is_available() else "cpu"
    print(
        f"{args.generator}, batch {args.batch} per device, {args.precision}, DDP graph: {args.graph}, "
        f"gradient_as_bucket_view={args.bucket_view}, comm hook {args.comm_hook}, "
        f"bucket_cap_mb {args.bucket_mb or 25}, compile {args.compile or 'off'}, "
        f"steps {args.warmup}..{args.warmup + args.steps}, on {name}"
    )
    print(f"{'devices':>8} {'pairs/s':>10} {'per device':>11} {'speed-up':>9}")
    for n, rate in rows:
        print(f"{n:>8} {rate:>10.1f} {rate / n:>11.1f} {rate / rows[0][1]:>8.2f}x")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"args": vars(args), "device": name, "pairs_per_s": dict(rows)}, f, indent=1)


if __name__ == "__main__":
    main()
