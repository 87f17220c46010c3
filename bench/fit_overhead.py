"""Benchmark of what a batched scene fit (``fit.batch_objects``) spends outside its training steps: building the
stacked model of K hash grids, and writing and reading the group's resume checkpoint (written every
``fit.checkpoint_every`` steps; it holds the K hash tables with their Adam state). The training loop waits for
the checkpoint's copy to the host only; it is serialised, written and flushed in a background thread.

    python bench/fit_overhead.py                        # sim_digit's 27 default hash grids, on the CPU
    python bench/fit_overhead.py --device cuda --objects 27

No capture needed: the scenes get a fixed bound. Prints seconds and sizes.
"""

from __future__ import annotations

import argparse
import platform
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--objects", type=int, default=27, help="hash grids in the group")
    ap.add_argument("--writes", type=int, default=2, help="checkpoint writes to time")
    ap.add_argument("--dir", default=None, help="where the checkpoint is written (default: a temporary folder)")
    args = ap.parse_args()

    import torch

    from tnf.registry import SCENES
    from tnf.scenes.batched import BatchedHashGrid, _read_resume, _resume_state, _write_resume

    def sync() -> None:
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()

    K = args.objects
    t = time.perf_counter()
    torch.manual_seed(0)
    scenes = [SCENES.build({"name": "hashgrid", "bound": 0.1}) for _ in range(K)]
    built = time.perf_counter() - t
    t = time.perf_counter()
    model = BatchedHashGrid(scenes).to(args.device)
    sync()
    stacked = time.perf_counter() - t
    opt = torch.optim.Adam(model.param_groups(0.01), lr=0.01, betas=(0.9, 0.99), eps=1e-15)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, 0.999)
    for p in model.parameters():
        p.grad = torch.zeros_like(p)
    opt.step()  # the Adam state a checkpoint holds
    sync()
    print(f"device {args.device}, {platform.processor() or platform.machine()}, torch {torch.__version__}")
    print(f"{K} hash grids: {model.encoding.table.numel() / 1e6:.0f} M table parameters")
    print(f"build {K} scenes: {built:.1f} s; stack them into one model on {args.device}: {stacked:.1f} s")
    with tempfile.TemporaryDirectory(dir=args.dir) as d:
        path = Path(d) / "group.pt"
        for i in range(args.writes):
            t = time.perf_counter()
            state = _resume_state({"bench": True}, 1000, 1.0, [[] for _ in range(K)], model, opt, sched)
            copied = time.perf_counter() - t
            t = time.perf_counter()
            _write_resume(path, state)
            written = time.perf_counter() - t
            print(
                f"checkpoint {i + 1}: copy to the host {copied:.1f} s (the training loop waits), serialise and "
                f"write {written:.1f} s (in the background), {path.stat().st_size / 2**30:.2f} GiB"
            )
        t = time.perf_counter()
        ckpt, why = _read_resume(path, {"bench": True})
        assert ckpt is not None, why
        print(f"checkpoint read: {time.perf_counter() - t:.1f} s")


if __name__ == "__main__":
    main()
