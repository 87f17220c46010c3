"""Throughput of the evaluation's classifier training and of SSIM/MSE scoring; prints the figures.

python bench/eval_classifier.py [--device cuda] [--images 4096] [--size 64]
"""

from __future__ import annotations

import argparse
import time

import torch

from tnf.eval.classify import ClassifierConfig, accuracy, train_classifier
from tnf.metrics import mse, ssim


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--images", type=int, default=2048)
    ap.add_argument("--size", type=int, default=64, help="classifier input side, pixels")
    ap.add_argument("--steps", type=int, default=100)
    a = ap.parse_args()
    x = torch.randint(0, 256, (a.images, 3, 128, 128), dtype=torch.uint8)
    y = torch.randint(0, 24, (a.images,))
    cfg = ClassifierConfig(image_size=a.size, steps=a.steps)
    train_classifier(x[:64], y[:64], 24, ClassifierConfig(image_size=a.size, steps=2), device=a.device)  # warm-up
    sync = torch.cuda.synchronize if a.device.startswith("cuda") else (lambda: None)
    t = time.perf_counter()
    model = train_classifier(x, y, 24, cfg, device=a.device)
    sync()
    dt = time.perf_counter() - t
    print(f"classifier training: {a.steps * cfg.batch_size / dt:,.0f} images/s ({a.size}px, batch {cfg.batch_size})")
    t = time.perf_counter()
    accuracy(model, x, y, a.size)
    print(f"classifier inference: {a.images / (time.perf_counter() - t):,.0f} images/s")
    p, q = x[:512].to(a.device), x.flip(0)[:512].to(a.device)
    ssim(p[:8], q[:8])
    t = time.perf_counter()
    ssim(p, q), mse(p, q)
    sync()
    print(f"SSIM+MSE scoring: {512 / (time.perf_counter() - t):,.0f} image pairs/s at 128x128")


if __name__ == "__main__":
    main()
