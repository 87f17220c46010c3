"""Benchmark of two phases of ``tnf evaluate`` at sim_digit's scale: reading the classification task's touches and
scoring the test images, as they were and as they are.

- ``classify.load``: per object, the Sim splits' touches (500 train touches of a 240 x 320 Digit), the 50
  novel-view test touches and the 200 generated touches (128 px). Before: every Sim touch read, one image at a
  time, to draw 20 of them; now: only the drawn touches, decoded in threads and resized together
  (``load_touch_images(rows=...)``). Timed on ``--objects`` objects and scaled to 27.
- ``metrics``: SSIM and MSE of the model's images and of the background (the BG row) on 3,000 test pairs (sim_digit's
  1,200 novel-view and 1,800 novel-object pairs) in batches of 64. Before: the generator's images copied to the
  CPU and scored there (float64); now: scored on ``--device``.

    python bench/evaluate.py                  # on CUDA if present
    python bench/evaluate.py --objects 1 --pairs 256    # a quick check on the CPU

Synthetic images from a fixed seed; needs torch, numpy and Pillow.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tnf.eval.classify import load_touch_images, subset, touch_count  # noqa: E402
from tnf.metrics import mse, ssim  # noqa: E402
from tnf.testing.references import load_touch_images_one_by_one  # noqa: E402


def _image(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.stack([60 + 0.1 * xx, 90 + 0.05 * yy, np.full((h, w), 150.0)], -1)
    cy, cx = rng.uniform(0.3, 0.7) * h, rng.uniform(0.3, 0.7) * w
    img += np.exp(-(((yy - cy) / 30) ** 2 + ((xx - cx) / 30) ** 2))[..., None] * np.array([80.0, 60.0, -40.0])
    return np.clip(img + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8)


def _folder(folder: Path, splits: dict[str, int], h: int, w: int, seed: int) -> Path:
    """A touch-format folder of ``splits`` touches (images/*.png, manifest.json)."""
    rng = np.random.default_rng(seed)
    (folder / "images").mkdir(parents=True)
    touches = []
    for split, n in splits.items():
        for _ in range(n):
            i = len(touches)
            Image.fromarray(_image(rng, h, w)).save(folder / "images" / f"{i:05d}.png")
            eye = [[float(r == c) for c in range(4)] for r in range(4)]
            touches.append({"index": i, "split": split, "image": f"images/{i:05d}.png", "start_c2w": eye})
    (folder / "manifest.json").write_text(json.dumps({"object": folder.name, "touches": touches}))
    return folder


def bench_load(root: Path, objects: int, size: int = 64, sim: int = 20) -> tuple[float, float]:
    """Seconds per object before and after."""
    folders = []
    for k in range(objects):
        touch = _folder(root / f"touch{k}", {"train": 500, "novel_view": 50}, 320, 240, k)
        gen = _folder(root / f"gen{k}", {"gen": 200}, 128, 128, 100 + k)
        folders.append((touch, gen))
    t0 = time.perf_counter()
    for touch, gen in folders:
        load_touch_images_one_by_one(touch, size, ["train"], None, 0)
        load_touch_images_one_by_one(touch, size, ["novel_view"], None, 0)
        load_touch_images_one_by_one(gen, size, None, None, 0)
    before = (time.perf_counter() - t0) / objects
    t0 = time.perf_counter()
    for touch, gen in folders:
        rows = subset(touch_count(touch, ["train"]), sim, 0)
        load_touch_images(touch, size, ["train"], rows=rows)
        load_touch_images(touch, size, ["novel_view"])
        load_touch_images(gen, size)
    after = (time.perf_counter() - t0) / objects
    return before, after


def bench_metrics(device: str, pairs: int, batch: int = 64) -> tuple[float, float]:
    g = torch.Generator().manual_seed(0)
    batches = []
    for start in range(0, pairs, batch):
        b = min(batch, pairs - start)
        bg = torch.full((b, 3, 128, 128), -0.2)
        target = (bg + torch.rand(b, 3, 128, 128, generator=g) * 0.3).clamp(-1, 1)
        batches.append((bg, target, (target * 0.9).to(device)))  # the model's images, made on the device

    def run(on_device: bool) -> float:
        def sync() -> None:
            if device.startswith("cuda"):
                torch.cuda.synchronize()

        sync()
        t0 = time.perf_counter()
        for bg, target, fake in batches:
            where = fake.device if on_device else target.device
            t, b, f = target.to(where), bg.to(where), fake.float().to(where)
            ssim(b, t).tolist(), mse(b, t).tolist(), ssim(f, t).tolist(), mse(f, t).tolist()
        sync()
        return time.perf_counter() - t0

    run(True)  # warm-up (the blur matrices, CUDA kernels)
    return run(False), run(True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--objects", type=int, default=3, help="objects timed (scaled to 27)")
    ap.add_argument("--pairs", type=int, default=3000, help="test pairs scored")
    args = ap.parse_args()
    name = torch.cuda.get_device_name() if args.device.startswith("cuda") else platform.processor() or "cpu"
    print(f"device {args.device} ({name}), {torch.get_num_threads()} CPU threads, torch {torch.__version__}")
    with tempfile.TemporaryDirectory() as tmp:
        before, after = bench_load(Path(tmp), args.objects)
    print(f"classify.load: {before:.2f} s -> {after:.2f} s per object; at 27 objects {27 * before:.1f} s -> "
          f"{27 * after:.1f} s")  # fmt: skip
    before, after = bench_metrics(args.device, args.pairs)
    print(f"metrics ({args.pairs} pairs, G and BG): on the CPU {before:.2f} s, on {args.device} {after:.2f} s")


if __name__ == "__main__":
    main()
