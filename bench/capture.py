"""Capture speed: views per second rendering built-in objects with pyrender at 128 x 128.

    python bench/capture.py [--objects can,mug,bolt] [--views 48] [--resolution 128] [--antialias 0]
                            [--compare] [--device cpu]

Two figures per object: ``render`` (rendering only, renderer warm) and ``capture`` (what ``tnf capture``
does per object once its mesh is built: swap the mesh into the one renderer, render, write the PNGs, depth
files and transforms.json through a thread pool). ``--compare`` also measures, in the same run, the
previous way (pyrender's 4x multisampling, a new renderer per object, files written after rendering at PNG
level 6). Mesh generation is not counted. The machine's load average is printed: other processes slow
every figure.

pyrender renders through EGL (Mesa llvmpipe on a CPU, the NVIDIA driver on a GPU machine), so ``--device``
only labels the output; the GPU is used when EGL finds one.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np


def _previous_capture(mesh, folder, train, cfg, k):  # type: ignore[no-untyped-def]
    """The capture before this benchmark's changes: a fresh 4x-multisampled renderer, files written after."""
    from PIL import Image

    from tnf.capture import write_transforms
    from tnf.capture.render import MeshRenderer

    r = MeshRenderer(mesh, cfg.resolution, cfg.resolution, antialias=4)
    r.antialias = 0  # buffers stay 4x multisampled; skips the depth pass at pixel centres, as before
    rgb, depth = r.render(train, k)
    r.close()
    (folder / "images").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(parents=True, exist_ok=True)
    meta = write_transforms(folder, "train", train, cfg)
    for frame, colour, z in zip(meta["frames"], rgb, depth):
        alpha = np.where(z > 0, 255, 0).astype(np.uint8)[..., None]
        Image.fromarray(np.concatenate([colour, alpha], -1), "RGBA").save(folder / frame["file_path"])
        np.save(folder / frame["depth_file_path"], z.astype(np.float32))


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--objects", default="ball,box,can,mug,bolt,vase")
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--antialias", type=int, default=0, help="multisample anti-aliasing samples (capture.antialias)")
    ap.add_argument("--compare", action="store_true", help="also time the previous capture, in the same run")
    ap.add_argument("--device", default="cpu", help="label only: EGL picks the GPU when there is one")
    args = ap.parse_args()

    from tnf.capture import CaptureConfig, camera_poses, intrinsics
    from tnf.capture.render import MeshRenderer, capture_object
    from tnf.objects.builtin import Builtin

    cfg = CaptureConfig(resolution=args.resolution, num_views=args.views, num_test_views=0, antialias=args.antialias)
    k = intrinsics(cfg)
    meshes = {name: Builtin().load(name) for name in args.objects.split(",")}
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())} ({os.cpu_count()} cores)")
    totals = {"render": [0, 0.0], "capture": [0, 0.0], "previous": [0, 0.0]}
    t = time.perf_counter()
    renderer = MeshRenderer(None, args.resolution, args.resolution, antialias=args.antialias)
    setup = time.perf_counter() - t
    with ThreadPoolExecutor(max_workers=2) as pool, tempfile.TemporaryDirectory() as tmp:
        for name, mesh in meshes.items():
            poses, _ = camera_poses(float(np.linalg.norm(mesh.vertices, axis=1).max()), cfg)
            t = time.perf_counter()
            renderer.set_mesh(mesh)
            capture_object(renderer, Path(tmp) / name, poses, poses[:0], cfg, pool)
            dt_capture = time.perf_counter() - t
            t = time.perf_counter()
            renderer.render(poses, k)
            dt_render = time.perf_counter() - t
            row = f"{name:12s} {len(mesh.faces):6d} triangles  render {len(poses) / dt_render:7.1f}  "
            row += f"capture {len(poses) / dt_capture:7.1f} views/s"
            for key, dt in (("render", dt_render), ("capture", dt_capture)):
                totals[key][0] += len(poses)
                totals[key][1] += dt
            if args.compare:
                t = time.perf_counter()
                _previous_capture(mesh, Path(tmp) / f"{name}_previous", poses, cfg, k)
                dt = time.perf_counter() - t
                totals["previous"][0] += len(poses)
                totals["previous"][1] += dt
                row += f"  previous capture {len(poses) / dt:7.1f} views/s"
            print(row)
    renderer.close()
    size = f"{args.resolution}x{args.resolution}"
    print(f"renderer set-up (EGL context): {setup:.2f} s once per process")
    for key, (n, s) in totals.items():
        if n:
            aa = 4 if key == "previous" else args.antialias
            print(f"overall {key}: {n / s:.1f} views/s at {size}, antialias {aa}")
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())} ({args.device})")


if __name__ == "__main__":
    main()
