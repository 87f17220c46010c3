"""Speed of the warp gel simulator: Digit frames per second at 120x160 and 240x320, and peak GPU memory.

    python bench/sim.py                       # CPU, batch 1 (per-frame latency, compared with TACTO)
    python bench/sim.py --device cuda --batch 512
    python bench/sim.py --examples results/sim  # also write example images (ball, edge, ridge)

TACTO (PyBullet + PyRender on Mesa) measured 43.5 ms per Digit frame at 120x160 and 67 ms at 240x320 on the
reference 2-core CPU machine; the goals are >= 5x faster on CPU and >= 5000 frames/s at 240x320 on one H100.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

os.environ.setdefault("WARP_CACHE_PATH", str(Path(__file__).resolve().parents[1] / ".warp-cache"))

import numpy as np  # noqa: E402
import trimesh  # noqa: E402
import warp as wp  # noqa: E402

from tnf.registry import SENSORS, SIMULATORS  # noqa: E402
from tnf.sim.touch import look_at  # noqa: E402

TACTO_MS = {(120, 160): 43.5, (240, 320): 67.0}


def poses(n: int, rng: np.random.Generator, radius: float = 0.05) -> np.ndarray:
    """Start poses looking at the origin from the upper hemisphere, jittered so touches differ."""
    out = []
    for _ in range(n):
        d = rng.normal(size=3) * 0.15 + np.array([0.0, 0.0, 1.0])
        d /= np.linalg.norm(d)
        out.append(look_at(radius * d, rng.normal(size=3) * 0.002))
    return np.stack(out)


def bench(device: str, size: tuple[int, int], batch: int, repeats: int, host: bool) -> dict:
    sensor = SENSORS.build({"name": "digit", "width": size[0], "height": size[1]})
    sim = SIMULATORS.build({"name": "warp_gel"}, sensor=sensor, device=device)
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=0.01)
    c2w = poses(batch, np.random.default_rng(0))
    sim.press(mesh, c2w, 3.0, host=host)  # compile and allocate
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for i in range(repeats):
        sim.press(mesh, c2w, 3.0, seed=i, host=host)
    wp.synchronize_device(device)
    dt = (time.perf_counter() - t0) / repeats
    out = {"ms_per_batch": dt * 1e3, "ms_per_frame": dt * 1e3 / batch, "fps": batch / dt}
    if device.startswith("cuda"):
        try:
            out["peak_gib"] = wp.get_mempool_used_mem_high(device) / 2**30
        except Exception:  # older warp without mempool statistics
            out["peak_gib"] = float("nan")
    return out


def examples(folder: Path, device: str) -> None:
    """Ball, edge and ridge pressed into a Digit, written as PNGs next to the background."""
    from PIL import Image

    sensor = SENSORS.build("digit")
    sim = SIMULATORS.build({"name": "warp_gel"}, sensor=sensor, device=device)
    folder.mkdir(parents=True, exist_ok=True)
    Image.fromarray(sim.background).save(folder / "digit_background.png")
    down = np.eye(4)
    down[2, 3] = 0.05
    box = trimesh.creation.box(extents=(0.04, 0.04, 0.02))
    box.apply_translation((0.012, 0.0, 0.0))  # its edge runs under the gel's middle
    ridge = trimesh.creation.cylinder(radius=0.003, height=0.06, sections=64)
    ridge.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    ridge.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 6, (0, 0, 1)))
    cases = {"ball": trimesh.creation.icosphere(subdivisions=5, radius=0.008), "edge": box, "ridge": ridge}
    for name, mesh in cases.items():
        out = sim.press(mesh, down[None], 4.0, seed=1)
        Image.fromarray(out.images[0]).save(folder / f"digit_{name}.png")
        print(f"{name}: penetration {out.penetration[0] * 1e3:.2f} mm, force {out.force[0]:.2f} N")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", help="warp device: cpu, cuda, cuda:N")
    ap.add_argument("--batch", type=int, default=None, help="touches per launch (default: 1 on cpu, 512 on cuda)")
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--host", action="store_true", help="include copying results to NumPy")
    ap.add_argument("--examples", type=Path, default=None, help="write example images into this folder")
    args = ap.parse_args()
    device = "cuda:0" if args.device == "cuda" else args.device
    wp.init()
    gpu = device.startswith("cuda")
    batch = args.batch or (512 if gpu else 1)
    repeats = args.repeats or (20 if gpu else 5)
    print(f"device {wp.get_device(device).name} ({device}), batch {batch}, repeats {repeats}, host copy {args.host}")
    for size in ((120, 160), (240, 320)):
        r = bench(device, size, batch, repeats, args.host)
        line = f"digit {size[0]}x{size[1]}: {r['ms_per_frame']:.3f} ms/frame, {r['fps']:.0f} frames/s"
        if not gpu:
            line += f"; TACTO {TACTO_MS[size]} ms/frame -> {TACTO_MS[size] / r['ms_per_frame']:.1f}x"
        if "peak_gib" in r:
            line += f"; peak GPU memory {r['peak_gib']:.2f} GiB"
        print(line, flush=True)
    if args.examples:
        examples(args.examples, device)


if __name__ == "__main__":
    main()
