"""Capture speed: views per second rendering built-in objects with pyrender at 128 x 128.

    python bench/capture.py [--objects can,mug,bolt] [--views 48] [--resolution 128] [--device cpu]

pyrender renders through EGL (Mesa llvmpipe on a CPU, the NVIDIA driver on a GPU machine), so ``--device``
only labels the output; the GPU is used when EGL finds one.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", default="ball,box,can,mug,bolt,vase")
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--device", default="cpu", help="label only: EGL picks the GPU when there is one")
    args = ap.parse_args()

    from tnf.capture import CaptureConfig, camera_poses, intrinsics
    from tnf.capture.render import MeshRenderer
    from tnf.objects.builtin import Builtin

    cfg = CaptureConfig(resolution=args.resolution, num_views=args.views, num_test_views=0)
    total_views, total_s = 0, 0.0
    for name in args.objects.split(","):
        mesh = Builtin().load(name)
        poses, _ = camera_poses(float(np.linalg.norm(mesh.vertices, axis=1).max()), cfg)
        r = MeshRenderer(mesh, args.resolution, args.resolution)
        r.render(poses[:1], intrinsics(cfg))  # warm-up: context, shader compilation, uploads
        t = time.perf_counter()
        r.render(poses, intrinsics(cfg))
        dt = time.perf_counter() - t
        r.close()
        total_views += len(poses)
        total_s += dt
        print(f"{name:12s} {len(mesh.faces):6d} triangles  {len(poses) / dt:7.1f} views/s")
    print(f"overall: {total_views / total_s:.1f} views/s at {args.resolution}x{args.resolution} ({args.device})")


if __name__ == "__main__":
    main()
