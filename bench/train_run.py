"""Whole `tnf train` runs, timed: eager against the networks through torch.compile (`train.compile=MODE`).

    python bench/train_run.py --pairs 12000 --epochs 3 --modes false,reduce-overhead

Writes a paired dataset of random images at 128 px (the speed of a step does not depend on what the images show;
a tenth of the pairs are validation pairs; bench/loading.py writes them), then runs `tnf train` once per mode, each
in its own process, with the same settings (tn_cgan, trainer=gpu with its bf16-mixed precision, batch 64 unless
overridden). Prints each run's wall time (start-up, compile, every epoch's steps and validation, checkpoints) and its
ratio to the first mode's.
Extra arguments after `--` go to every `tnf train` call (for example `trainer.precision=32-true`).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from loading import build  # bench/loading.py: random pairs through PairWriter


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", type=int, default=12000)
    p.add_argument("--epochs", type=int, default=3)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--modes", default="false,reduce-overhead", help="train.compile values, comma-separated")
    p.add_argument("--trainer", default="gpu")
    p.add_argument("--data-root", help="keep the dataset and runs here (default: a temporary folder)")
    p.add_argument("extra", nargs="*", help="more overrides for every run (after --)")
    args = p.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.data_root or tmp)
        t0 = time.perf_counter()
        build(root / "pairs" / "digit-hashgrid", args.pairs, per_object=1000, val_every=10, sensor="digit")
        print(f"dataset: {args.pairs} pairs at 128 px in {time.perf_counter() - t0:.1f} s", flush=True)
        walls: dict[str, float] = {}
        for mode in args.modes.split(","):
            cmd = [
                sys.executable, "-m", "tnf.cli", "train", f"data_root={root}", f"trainer={args.trainer}",
                "progress=false", f"train.epochs={args.epochs}", "train.decay_epochs=0",
                f"data.batch_size={args.batch}", f"train.compile={mode}", f"train.run_name=compile-{mode}", *args.extra,
            ]  # fmt: skip
            t0 = time.perf_counter()
            done = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "COLUMNS": "200"})
            walls[mode] = time.perf_counter() - t0
            if done.returncode != 0:
                print(done.stdout[-3000:], done.stderr[-3000:], sep="\n")
                raise SystemExit(f"train.compile={mode} failed (exit {done.returncode})")
            summary = [line for line in done.stdout.splitlines() if "epochs on" in line or "val SSIM" in line]
            print(f"train.compile={mode}: {walls[mode]:.1f} s; {' '.join(summary)}", flush=True)
        first = next(iter(walls.values()))
        for mode, wall in walls.items():
            print(f"{mode:>28}: {wall:7.1f} s  ({first / wall:.2f}x the first)")


if __name__ == "__main__":
    main()
