"""Whole `tnf train` runs, timed: eager against the networks through torch.compile (`train.compile=MODE`).

    python bench/train_run.py --pairs 12000 --epochs 3 --modes false,reduce-overhead

Writes a paired dataset of random images at 128 px (the speed of a step does not depend on what the images show;
a tenth of the pairs are validation pairs), then runs `tnf train` once per mode, each in its own process, with the
same settings (tn_cgan, trainer=gpu, its precision, batch 64 unless overridden). Prints each run's wall time
(start-up, compile, every epoch's steps and validation, checkpoints) and its ratio to the first mode's.
Extra arguments after `--` go to every `tnf train` call (for example `trainer.precision=bf16-mixed`).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from tnf.data import SPLITS, PairWriter, write_manifest


def write_random_pairs(folder: Path, n: int, size: int = 128, seed: int = 0, chunk: int = 1000) -> None:
    """``n`` pairs of random uint8 images and float16 depth at ``size`` px; every tenth pair is a validation pair."""
    rng = np.random.default_rng(seed)
    background = rng.integers(0, 256, (1, size, size, 3), dtype=np.uint8)
    with PairWriter(folder, n, background) as w:
        for start in range(0, n, chunk):
            m = min(chunk, n - start)
            idx = np.arange(start, start + m)
            w.write(
                start,
                rgb=rng.integers(0, 256, (m, size, size, 3), dtype=np.uint8),
                depth=rng.random((m, size, size), dtype=np.float32).astype(np.float16),
                tactile=rng.integers(0, 256, (m, size, size, 3), dtype=np.uint8),
                background_index=np.zeros(m, np.int32),
                object_id=(idx % 2).astype(np.int32),
                split=np.where(idx % 10 == 9, SPLITS.index("val"), SPLITS.index("train")).astype(np.int8),
                touch_index=idx.astype(np.int32),
                sensor_id=np.zeros(m, np.int16),
            )
    record = {"name": "digit", "config": {}}
    write_manifest(folder, {"objects": ["a", "b"], "sensors": ["digit"], "sensor": record, "count": n})


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
        write_random_pairs(root / "pairs" / "digit-hashgrid", args.pairs)
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
