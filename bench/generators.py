"""Generator speed: training pairs per second and generated images per second at 128 x 128.

    python bench/generators.py --device cuda [--generators tn_cgan,lee,cyclegan] [--steps 30] [--json out.json]
    python bench/generators.py --device cuda --generators cyclegan --compile   # networks through torch.compile
    python bench/generators.py --device cuda --generators cyclegan --train-batches 64:bf16 --profile
    python bench/generators.py --device cpu --flops    # FLOPs per pair of one training step (counted, not timed)

A generator may carry config overrides after colons: ``--generators tn_cgan,tn_cgan:lambda_gan=1`` times
tn_cgan with its defaults (no adversarial term) and with the paper's cGAN term. A list value is JSON, its commas
inside the brackets: ``tn_cgan:inputs=["rgb","depth","background","depth_slope"]``.

Training runs each generator's own training step (with its defaults, tn_cgan's updates only the generator;
Lee's and CycleGAN's also their discriminators) on random batches already on the device, as ``tnf train``
does inside Lightning: fp32 at batch 64 (TF32 convolutions), bf16 autocast at batch 64 (what ``trainer=gpu``
trains sim_digit with: ``bf16-mixed``, ``data.batch_size=64``) and at batch 256, channels-last memory.
Generation runs ``generate`` in eval mode under ``inference_mode`` with bf16 autocast. Batches carry a force
(1-8 N), so ``tn_cgan:force=plane`` and ``tn_cgan:force=film`` time the force-conditioned generator
(``generator=tn_cgan_force``, docs/force.md). On a CPU use small
``--steps`` and batches (``--train-batches 8:fp32 --gen-batch 32``).
"""

from __future__ import annotations

import argparse
import json
import re
import time
from contextlib import nullcontext

import torch


def batch_on(device: str, n: int, size: int = 128, channels_last: bool = True) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    out = {
        "rgb": torch.rand(n, 3, size, size, generator=g) * 2 - 1,
        "depth": torch.rand(n, 1, size, size, generator=g) * 2 - 1,
        "background": torch.rand(n, 3, size, size, generator=g) * 2 - 1,
        "tactile": torch.rand(n, 3, size, size, generator=g) * 2 - 1,
    }
    fmt = torch.channels_last if channels_last else torch.contiguous_format
    batch = {k: v.to(device).contiguous(memory_format=fmt) for k, v in out.items()}
    batch["force"] = (1 + 7 * torch.rand(n, generator=g)).to(device)  # newtons, for a force-conditioned generator
    return batch


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def parse_spec(spec: str) -> dict:
    """``name[:key=value...]`` -> the generator's config dict; values are read as JSON where they parse."""
    name, *pairs = spec.split(":")
    out: dict = {"name": name}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep:
            raise SystemExit(f"override {pair!r} of {spec!r} is not key=value")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def build(spec: str, device: str, channels_last: bool, compile_nets: str = ""):
    from tnf.registry import GENERATORS

    g = GENERATORS.build(parse_spec(spec)).to(device)
    if channels_last:
        g = g.to(memory_format=torch.channels_last)
    if compile_nets:  # each network (net_g, net_d, ...) through torch.compile; the training step stays eager
        from tnf.generators.system import compile_networks

        compile_networks(g, compile_nets)
    return g


def bench_train(
    name: str,
    device: str,
    batch: int,
    bf16: bool,
    steps: int,
    channels_last: bool,
    compile_nets: str = "",
    profile: bool = False,
) -> float:
    """Training pairs per second; with ``profile``, also print the step's busiest operators by device time."""
    from tnf.generators import PlainOptimisation

    g = build(name, device, channels_last, compile_nets).train()
    opt = PlainOptimisation(g)
    data = batch_on(device, batch, channels_last=channels_last)
    amp = torch.autocast(device.split(":")[0], dtype=torch.bfloat16) if bf16 else nullcontext()
    for _ in range(3):  # warm-up: cuDNN autotuning, allocator
        with amp:
            g.training_step(data, opt)
    sync(device)
    t = time.perf_counter()
    for _ in range(steps):
        with amp:
            g.training_step(data, opt)
    sync(device)
    rate = steps * batch / (time.perf_counter() - t)
    if profile:
        acts = [torch.profiler.ProfilerActivity.CPU]
        if device.startswith("cuda"):
            acts.append(torch.profiler.ProfilerActivity.CUDA)
        with torch.profiler.profile(activities=acts) as prof:
            for _ in range(5):
                with amp:
                    g.training_step(data, opt)
            sync(device)
        key = "device_time_total" if device.startswith("cuda") else "cpu_time_total"
        print(f"{name}, 5 steps of batch {batch}:", flush=True)
        print(prof.key_averages().table(sort_by=key, row_limit=25, max_name_column_width=70), flush=True)
    return rate


def train_flops(name: str, device: str, batch: int = 2) -> float:
    """Floating-point operations of one training step per pair (forward and backward, every network), as torch's
    FlopCounterMode counts them (convolutions and matrix products; norms and pointwise ops are not counted)."""
    from torch.utils.flop_counter import FlopCounterMode

    from tnf.generators import PlainOptimisation

    g = build(name, device, channels_last=False).train()
    opt = PlainOptimisation(g)
    data = batch_on(device, batch, channels_last=False)
    g.training_step(data, opt)  # the first step allocates the optimiser's state
    with FlopCounterMode(display=False) as counter:
        g.training_step(data, opt)
    return counter.get_total_flops() / batch


def bench_generate(name: str, device: str, batch: int, steps: int, channels_last: bool) -> float:
    g = build(name, device, channels_last).eval()
    data = batch_on(device, batch, channels_last=channels_last)
    amp = torch.autocast(device.split(":")[0], dtype=torch.bfloat16)
    with torch.inference_mode(), amp:
        for _ in range(3):
            g.generate(data)
        sync(device)
        t = time.perf_counter()
        for _ in range(steps):
            g.generate(data)
        sync(device)
    return steps * batch / (time.perf_counter() - t)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--generators", default="tn_cgan,lee,cyclegan")
    ap.add_argument("--steps", type=int, default=30, help="timed steps per measurement")
    ap.add_argument("--train-batches", default="64:fp32,64:bf16,256:bf16", help="batch:precision pairs for training")
    ap.add_argument("--gen-batch", type=int, default=1024, help="images per generate call")
    ap.add_argument("--no-channels-last", action="store_true")
    ap.add_argument(
        "--compile", nargs="?", const="default", default="", help="train with each network through torch.compile (mode)"
    )
    ap.add_argument("--profile", action="store_true", help="also print each training step's busiest operators")
    ap.add_argument("--json", default=None, help="also write the figures to this JSON file")
    ap.add_argument("--flops", action="store_true", help="only count each generator's training FLOPs per pair")
    args = ap.parse_args()

    if args.device.startswith("cuda"):
        torch.backends.cudnn.benchmark = True
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    cl = not args.no_channels_last
    name_dev = torch.cuda.get_device_name(0) if args.device.startswith("cuda") else "cpu"
    print(f"device: {name_dev}; torch {torch.__version__}; channels_last={cl}")
    results = {"device": name_dev, "torch": torch.__version__, "channels_last": cl, "train": {}, "generate": {}}
    results["compile"] = args.compile
    names = re.split(r",(?![^\[]*\])", args.generators)
    if args.flops:
        for name in names:
            flops = train_flops(name, args.device)
            print(f"flops    {name:9s} {flops / 1e9:7.1f} GFLOP per pair per training step", flush=True)
        return
    for name in names:
        for spec in args.train_batches.split(","):
            b, prec = spec.split(":")
            rate = bench_train(name, args.device, int(b), prec == "bf16", args.steps, cl, args.compile, args.profile)
            tag = f"/compiled-{args.compile}" if args.compile else ""
            results["train"][f"{name}/{prec}/b{b}{tag}"] = rate
            print(f"train    {name:9s} {prec:5s} batch {int(b):4d}{tag}: {rate:9.0f} pairs/s", flush=True)
            if args.device.startswith("cuda"):
                torch.cuda.empty_cache()
        rate = bench_generate(name, args.device, args.gen_batch, args.steps, cl)
        results["generate"][f"{name}/bf16/b{args.gen_batch}"] = rate
        print(f"generate {name:9s} bf16  batch {args.gen_batch:4d}: {rate:9.0f} images/s", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=2)


if __name__ == "__main__":
    main()
