"""Paired-dataset benchmark: build a dataset by streaming (peak RAM) and load batches (pairs per second).

    python bench/loading.py                      # 13,500 pairs (the paper's 27 objects x 500 touches)
    python bench/loading.py --pairs 2000 --workers 2 --device cuda

Building writes random images through ``PairWriter`` in object-sized chunks, as ``tnf pair`` assembles its
caches. Loading reads from the page cache (one warm-up epoch first) with ``PairDataModule``'s loader and
converts to float32 [-1, 1] tensors; with ``--device cuda`` each batch is also copied to the GPU.
Prints build time, peak RSS while building, loading pairs/s and peak RSS while loading, and the machine's
load average (other processes slow every figure; with a busy machine ``--threads 1`` beats 2). Pairs per
CPU-second of the loading process (all its threads; workers not counted) depend less on the other processes.
Page faults per batch count first touches of memory (freshly allocated batches the C library had given back).
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def rss_mib() -> float:
    """Current resident set size of this process, MiB (includes the memory-mapped dataset pages it touched)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / 2**20


def anon_mib() -> float:
    """Resident anonymous memory (heap, batches; not file-backed memory maps), MiB."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("RssAnon:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def minor_faults() -> int:
    """Minor page faults of this process so far (first touches of memory it was given, mapped file pages)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def build(folder: Path, n: int, per_object: int, val_every: int = 0, sensor: str = "bench") -> tuple[float, float]:
    """Write ``n`` random 128 px pairs, ``per_object`` per object (one write each); with ``val_every`` > 0 every
    ``val_every``-th pair of an object is a validation pair (all train otherwise). -> (seconds, peak RSS MiB)."""
    from tnf.data import SPLITS, PairWriter, write_manifest

    rng = np.random.default_rng(0)
    objects = (n + per_object - 1) // per_object
    peak = rss_mib()
    t0 = time.perf_counter()
    with PairWriter(folder, n, rng.integers(0, 256, (1, 128, 128, 3), dtype=np.uint8)) as w:
        for o in range(objects):
            s, e = o * per_object, min(n, (o + 1) * per_object)
            k = e - s
            w.write(
                s,
                rgb=rng.integers(0, 256, (k, 128, 128, 3), dtype=np.uint8),
                depth=rng.random((k, 128, 128), dtype=np.float32).astype(np.float16),
                tactile=rng.integers(0, 256, (k, 128, 128, 3), dtype=np.uint8),
                background_index=np.zeros(k, np.int32),
                object_id=np.full(k, o, np.int32),
                split=np.where(
                    (np.arange(k) % val_every == val_every - 1) if val_every > 0 else np.zeros(k, bool),
                    SPLITS.index("val"),
                    SPLITS.index("train"),
                ).astype(np.int8),
                touch_index=np.arange(k, dtype=np.int32),
                sensor_id=np.zeros(k, np.int16),
            )
            peak = max(peak, rss_mib())
    record = {"name": sensor, "config": {}}  # the sensor record `tnf pair` writes
    names = [f"o{i}" for i in range(objects)]
    write_manifest(folder, {"objects": names, "sensors": [sensor], "sensor": record, "count": n})
    return time.perf_counter() - t0, peak


def write_floor(batch_size: int, repeats: int = 30) -> float:
    """Pairs/s at which this process can allocate and write the float32 tensors of a batch once (7 channels of
    128 x 128 per pair): an upper bound for any loader that serves float batches."""
    shapes = [(batch_size, 128, 128, 3), (batch_size, 1, 128, 128), (batch_size, 128, 128, 3)]
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for shape in shapes:
            torch.empty(shape).fill_(0.5)
        times.append(time.perf_counter() - t0)
    return batch_size / float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pairs", type=int, default=13500, help="pairs in the dataset")
    ap.add_argument("--per-object", type=int, default=500, help="pairs per object (write chunk)")
    ap.add_argument("--batch-size", type=int, default=64)
    ap.add_argument("--workers", type=int, default=0, help="DataLoader workers")
    ap.add_argument("--threads", type=int, default=2, help="torch threads in the loading process")
    ap.add_argument("--epochs", type=int, default=2, help="timed epochs after one warm-up epoch")
    ap.add_argument("--device", default="cpu", help="cpu or cuda (batches copied there, pinned memory)")
    ap.add_argument("--folder", default=None, help="where to build (default a temporary folder, removed)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    tmp = Path(args.folder) if args.folder else Path(tempfile.mkdtemp(prefix="tnf-bench-pairs-"))
    folder = tmp / "bench"
    try:
        rss0 = rss_mib()
        secs, peak = build(folder, args.pairs, args.per_object)
        size = sum(p.stat().st_size for p in folder.glob("*.npy")) / 2**30
        print(
            f"build: {args.pairs} pairs, {size:.2f} GiB on disk in {secs:.1f} s; "
            f"peak RSS {peak:.0f} MiB (start {rss0:.0f}; anonymous now {anon_mib():.0f} MiB)"
        )

        from tnf.data import PairDataModule

        cuda = args.device.startswith("cuda")
        floor = write_floor(args.batch_size)
        print(
            f"floor: {floor:,.0f} pairs/s to allocate and fill a float batch once (rgb, depth, tactile; the "
            "background is one shared image), no reading or converting"
        )
        for compact in (False, True):
            dm = PairDataModule(
                [folder],
                batch_size=args.batch_size,
                num_workers=args.workers,
                pin_memory=cuda,
                drop_last=True,
                convert_on_device=compact,
            )
            loader = dm.train_dataloader()
            rss_before = rss_mib()
            peak = rss_before

            def epoch(loader=loader, dm=dm) -> int:
                nonlocal peak
                n = 0
                for batch in loader:
                    batch = {k: v.to(args.device, non_blocking=True) for k, v in batch.items()}
                    batch = dm.on_after_batch_transfer(batch, 0)  # float32 [-1, 1] from here on
                    n += len(batch["rgb"])
                    peak = max(peak, rss_mib())
                if cuda:
                    torch.cuda.synchronize()
                return n

            epoch()  # warm-up: pages into the cache, workers started
            t0, cpu0, faults0 = time.perf_counter(), time.process_time(), minor_faults()
            n = sum(epoch() for _ in range(args.epochs))
            secs, cpu = time.perf_counter() - t0, time.process_time() - cpu0
            faults = (minor_faults() - faults0) / (n / args.batch_size)
            mode = "compact batches, converted on " + args.device if compact else "float batches from the loader"
            print(
                f"load ({mode}): {n / secs:,.0f} pairs/s, {n / cpu:,.0f} pairs per CPU-second of the main process "
                f"(batch {args.batch_size}, workers {args.workers}, "
                f"threads {args.threads}; {faults:,.0f} page faults per batch); "
                f"RSS {rss_before:.0f} -> peak {peak:.0f} MiB in the main process "
                f"(anonymous, i.e. not the memory-mapped arrays: {anon_mib():.0f} MiB); "
                f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores"
            )
            del loader, dm
    finally:
        if not args.folder:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
