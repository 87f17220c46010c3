"""Benchmark of the classification task's training: every row and restart one after another, against all at once.

Builds a classification task at sim_digit's scale (27 objects; per object 20 ground-truth touches in the Sim set,
200 generated touches, 50 novel-view test touches; rows Sim, Sim + G, G only; the classifier of
``conf/evaluate/default.yaml`` with sim_digit's ``real_fraction: 0.5``) from synthetic uint8 tactile-like images
with a fixed seed, trains every classifier of the task with the reference loop
(``train_classifier_sequential``, one classifier at a time) and with ``train_classifiers`` (all at once, or
``--at-once N`` per network), and prints the seconds per classifier of each, their ratio and the rows'
accuracies of both. Warm-up runs of both (a few steps on the same shapes) come first and are not timed.

    python bench/classify.py                        # sim_digit's scale, on CUDA if present
    python bench/classify.py --scale quickstart     # the quick start's task (6 objects, 5 restarts)
    python bench/classify.py --tiny                 # a quick check on the CPU

Needs only torch, numpy and PyYAML: ``tnf.eval.classify`` and what it imports (tnf's Config classes read their
defaults from ``conf/`` with PyYAML where omegaconf is missing).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import platform
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

# Each scale: the classifier's settings, then the task (classes, images per class of each kind, which rows).
SCALES: dict[str, dict[str, Any]] = {
    # conf/evaluate/default.yaml's classifier and classify nodes with conf/experiment/sim_digit.yaml's overrides;
    # 200 generated touches per object (generate.n_poses) and 50 novel-view test touches (touch.n_novel_view).
    "sim_digit": {
        "classifier": dict(
            image_size=64, width=32, steps=1500, batch_size=64, lr=1e-3, weight_decay=1e-4, shift=4,
            real_fraction=0.5, restarts=1,
        ),
        "classes": 27, "sim": 20, "generated": 200, "test": 50, "generated_only": True,
    },
    # conf/experiment/quickstart.yaml: 6 objects, 5 Sim touches, 40 generated and 30 test touches per object.
    "quickstart": {
        "classifier": dict(
            image_size=32, width=16, steps=300, batch_size=64, lr=1e-3, weight_decay=1e-4, shift=4,
            real_fraction=0.5, restarts=5,
        ),
        "classes": 6, "sim": 5, "generated": 40, "test": 30, "generated_only": False,
    },
    "tiny": {
        "classifier": dict(
            image_size=32, width=8, steps=80, batch_size=16, lr=3e-3, weight_decay=1e-4, shift=2,
            real_fraction=0.5, restarts=2,
        ),
        "classes": 4, "sim": 6, "generated": 12, "test": 8, "generated_only": True,
    },
}  # fmt: skip


def images_of(labels: np.ndarray, size: int, rng: np.random.Generator, generated: bool = False) -> torch.Tensor:
    """Tactile-like uint8 images ``[N, 3, size, size]`` of classes ``labels`` ``[N]``: a bluish background with an
    elongated blob whose orientation, elongation and tint depend on the class, at a random place and scale, with
    pixel noise. Generated images are a little smoother and brighter (a domain gap)."""
    n = len(labels)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size
    angle = (labels % 9) * (math.pi / 9) + rng.normal(0, 0.08, n)
    elong = np.array([1.4, 2.2, 3.2])[(labels // 9) % 3] * rng.uniform(0.85, 1.15, n)
    scale = rng.uniform(0.08, 0.14, n)
    cy, cx = rng.uniform(0.3, 0.7, n), rng.uniform(0.3, 0.7, n)
    tint = np.stack([np.cos(labels * 0.7), np.sin(labels * 0.7), np.cos(labels * 1.3)], -1) * 25.0
    c, s = np.cos(angle)[:, None, None], np.sin(angle)[:, None, None]
    dy, dx = yy[None] - cy[:, None, None], xx[None] - cx[:, None, None]
    u, v = c * dx + s * dy, -s * dx + c * dy
    blob = np.exp(-((u / (scale * elong)[:, None, None]) ** 2 + (v / scale[:, None, None]) ** 2))
    base = np.stack([60 + 40 * xx, 90 + 20 * yy, np.full_like(xx, 150)], 0)[None]
    img = base + blob[:, None] * (np.array([80.0, 60.0, -40.0])[None, :] + tint)[..., None, None]
    img = img + rng.normal(0, 5.0 if generated else 8.0, img.shape) + (4.0 if generated else 0.0)
    return torch.from_numpy(np.clip(img, 0, 255).astype(np.uint8))


def task(classify: ModuleType, scale: dict[str, Any], size: int, seed: int) -> tuple[Any, Any, Any]:
    """(rows as a function of a restart's seed, the test set, the Sim pool): as ``tnf evaluate`` builds them, each
    restart drawing its own Sim touches from a pool of 4 times as many per class."""
    li = classify.LabelledImages
    rng = np.random.default_rng(seed)
    k = scale["classes"]

    def labelled(per_class: int, generated: bool = False) -> Any:
        labels = np.repeat(np.arange(k), per_class)
        x = images_of(labels, size, rng, generated)
        return li(x, torch.from_numpy(labels), torch.full((len(labels),), generated))

    pool, gen, test = labelled(4 * scale["sim"]), labelled(scale["generated"], True), labelled(scale["test"])

    def rows(run_seed: int) -> dict[str, Any]:
        idx = torch.from_numpy(classify.subset(len(pool), scale["sim"] * k, run_seed))
        sim = li(pool.images[idx], pool.labels[idx])
        out = {"Sim": sim, "Sim + G": li.concat([sim, gen])}
        if scale["generated_only"]:
            out["G only"] = gen
        return out

    return rows, test, pool


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scale", choices=sorted(SCALES), default="sim_digit")
    ap.add_argument("--tiny", action="store_true", help="the tiny scale (same as --scale tiny)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--restarts", type=int, default=None, help="classifiers per row (default: the scale's)")
    ap.add_argument("--steps", type=int, default=None, help="optimisation steps (default: the scale's)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--at-once", type=int, default=None, help="classifiers per network (default: all of them)")
    ap.add_argument("--skip-sequential", action="store_true", help="time the batched training only")
    a = ap.parse_args()
    name = "tiny" if a.tiny else a.scale
    scale = SCALES[name]
    from tnf.eval import classify

    cfg = classify.ClassifierConfig(**scale["classifier"])
    if name == "sim_digit":
        default = dataclasses.replace(classify.ClassifierConfig(), real_fraction=0.5)
        if default != cfg:
            print(f"note: conf/ now gives sim_digit {default}; this benchmark uses {cfg}")
    over = {k: v for k, v in (("restarts", a.restarts), ("steps", a.steps)) if v is not None}
    cfg = dataclasses.replace(cfg, **over)
    cfg.validate()
    rows, test, _ = task(classify, scale, cfg.image_size, a.seed)
    runs = [  # (row, set, seed) of every classifier, as run_rows orders them
        (row, s, seed)
        for seed in (classify.restart_seed(a.seed, k) for k in range(cfg.restarts))
        for row, s in rows(seed).items()
    ]
    sets, seeds = [s for _, s, _ in runs], [seed for *_, seed in runs]
    at_once = a.at_once or len(sets)
    dev = torch.device(a.device)
    cuda = dev.type == "cuda"
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    where = torch.cuda.get_device_name(dev) if cuda else f"CPU ({platform.processor() or platform.machine()})"
    print(f"{name}: {len(sets)} classifiers ({len(sets) // cfg.restarts} rows x {cfg.restarts} restarts) on {where}")
    print(f"  torch {torch.__version__}, {torch.get_num_threads()} CPU threads")
    print(f"  training sets {sorted({len(s) for s in sets})} images, test {len(test)} images, {cfg}")
    print(f"  batched: {at_once} classifiers per network (train_classifiers' default: all on a GPU, 1 on the CPU)")

    def sequential(c: Any) -> list[Any]:
        return [
            classify.train_classifier_sequential(s.images, s.labels, scale["classes"], c, seed, a.device, s.generated)
            for s, seed in zip(sets, seeds, strict=True)
        ]

    def batched(c: Any) -> list[Any]:
        return classify.train_classifiers(sets, scale["classes"], c, seeds, a.device, at_once=at_once)

    def timed(train: Any) -> tuple[float, list[Any]]:
        train(dataclasses.replace(cfg, steps=3))  # warm-up: the same shapes, untimed
        sync()
        t = time.perf_counter()
        models = train(cfg)
        sync()
        return time.perf_counter() - t, models

    def accuracies(models: list[Any]) -> dict[str, float]:
        acc: dict[str, float] = {}
        for (row, _, _), m in zip(runs, models, strict=True):
            acc[row] = acc.get(row, 0.0) + classify.accuracy(m, test.images, test.labels, cfg.image_size) / cfg.restarts
        return acc

    results = {}
    for label, train in [("batched", batched)] + ([] if a.skip_sequential else [("sequential", sequential)]):
        seconds, models = timed(train)
        results[label] = seconds
        acc = ", ".join(f"{row} {v:.1f} %" for row, v in accuracies(models).items())
        print(f"{label:>10}: {seconds:8.2f} s, {seconds / len(sets):7.3f} s per classifier; accuracy {acc}")
    if "sequential" in results:
        print(f"  sequential / batched: {results['sequential'] / results['batched']:.2f}x")


if __name__ == "__main__":
    main()
