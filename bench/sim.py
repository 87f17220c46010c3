"""Speed of the warp gel simulator: Digit frames per second at 120x160 and 240x320, per phase, and peak memory.

    python bench/sim.py                       # CPU: batches of 16 touches on builtin objects, 3 measurements
    python bench/sim.py --device cuda --batch 512
    python bench/sim.py --examples results/sim  # also write example images (ball, edge, ridge)

Each measurement presses the sensor onto several builtin objects (and an icosphere) from poses around them, a
batch per object, and counts every frame: ray cast, force solve, deformation, shading, blur and noise (and the
copy to NumPy with ``--host``). It is repeated ``--runs`` times (the machine may be shared): best and median are
printed, as wall-clock time and as this process's CPU time (what the frames cost when cores are free).

TACTO (PyBullet + PyRender on Mesa) measured 43.5 ms per Digit frame at 120x160 and 67 ms at 240x320 on the
reference 2-core CPU machine; the goals are >= 5x faster on that CPU and >= 5000 frames/s at 240x320 on one H100.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import time
from pathlib import Path

os.environ.setdefault("WARP_CACHE_PATH", str(Path(__file__).resolve().parents[1] / ".warp-cache"))

import numpy as np  # noqa: E402
import trimesh  # noqa: E402
import warp as wp  # noqa: E402

from tnf.registry import OBJECTS, SENSORS, SIMULATORS  # noqa: E402
from tnf.runtime import init_warp  # noqa: E402
from tnf.sim.touch import sphere_directions, start_poses  # noqa: E402

TACTO_MS = {(120, 160): 43.5, (240, 320): 67.0}  # ms per Digit frame, TACTO on the reference 2-core CPU
OBJECTS_USED = ("golf_ball", "gear", "mug", "wrench", "sponge")


def workload(batch: int) -> list[tuple[str, trimesh.Trimesh, np.ndarray]]:
    """(name, mesh, ``[batch, 4, 4]`` start poses) per object: poses on a sphere 3 cm beyond the object."""
    src = OBJECTS.build({"name": "builtin"})
    meshes = [(name, src.load(name)) for name in OBJECTS_USED]
    meshes.append(("icosphere", trimesh.creation.icosphere(subdivisions=5, radius=0.01)))
    out = []
    for k, (name, mesh) in enumerate(meshes):
        rng = np.random.default_rng(k)
        radius = float(np.linalg.norm(mesh.vertices, axis=1).max()) + 0.03
        out.append((name, mesh, start_poses(rng, sphere_directions(rng, batch, (0, 0, 1), 0, False), radius)))
    return out


def bench(device: str, size: tuple[int, int], batch: int, runs: int, host: bool) -> dict:
    sensor = SENSORS.build({"name": "digit", "width": size[0], "height": size[1]})
    sim = SIMULATORS.build({"name": "warp_gel"}, sensor=sensor, device=device)
    work = workload(batch)
    forces = np.linspace(1.0, 8.0, batch)
    for _, mesh, c2w in work:  # compile, build the meshes' BVHs, allocate
        sim.press(mesh, c2w, forces, host=host)
    wp.synchronize_device(device)
    frames = batch * len(work)
    walls, cpus, phases = [], [], []
    for run in range(runs):
        sim.timings = {}
        t0, c0 = time.perf_counter(), time.process_time()
        for i, (_, mesh, c2w) in enumerate(work):
            sim.press(mesh, c2w, forces, seed=run * 100 + i, host=host)
        wp.synchronize_device(device)
        walls.append((time.perf_counter() - t0) * 1e3 / frames)
        cpus.append((time.process_time() - c0) * 1e3 / frames)
        phases.append({k: v * 1e3 / frames for k, v in sim.timings.items()})
    sim.timings = None
    best = int(np.argmin(walls))
    out = {"wall": walls, "cpu": cpus, "phases": phases[best], "frames": frames}
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
    ap.add_argument("--batch", type=int, default=None, help="touches per launch (default: 16 on cpu, 512 on cuda)")
    ap.add_argument("--runs", type=int, default=3, help="measurements per resolution (best and median printed)")
    ap.add_argument("--host", action="store_true", help="include copying results to NumPy")
    ap.add_argument("--examples", type=Path, default=None, help="write example images into this folder")
    args = ap.parse_args()
    device = "cuda:0" if args.device == "cuda" else args.device
    init_warp()
    gpu = device.startswith("cuda")
    batch = args.batch or (512 if gpu else 16)
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(f"device {wp.get_device(device).name} ({device}), {os.cpu_count()} CPU cores, load average {load}")
    print(f"batch {batch}, objects {', '.join(OBJECTS_USED)}, icosphere; {args.runs} runs; host copy {args.host}")
    for size in ((120, 160), (240, 320)):
        r = bench(device, size, batch, args.runs, args.host)
        wall, cpu = r["wall"], r["cpu"]
        name = f"digit {size[0]}x{size[1]}"
        print(
            f"{name}: {r['frames']} frames/run; wall ms/frame best {min(wall):.2f} median {statistics.median(wall):.2f}"
            f" ({1e3 / min(wall):.0f} frames/s); CPU ms/frame best {min(cpu):.2f} median {statistics.median(cpu):.2f}"
        )
        if not gpu:
            ref = TACTO_MS[size]
            print(
                f"  vs TACTO {ref} ms/frame (measured on the reference 2-core CPU): {ref / min(wall):.1f}x wall (best),"
                f" {ref / statistics.median(wall):.1f}x wall (median), {ref / min(cpu):.1f}x CPU time (best)"
            )
        print("  phases (ms/frame, best run): " + ", ".join(f"{k} {v:.2f}" for k, v in r["phases"].items()))
        if "peak_gib" in r:
            print(f"  peak GPU memory (warp mempool) {r['peak_gib']:.2f} GiB")
        print(f"  peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10:.0f} MiB", flush=True)
    if args.examples:
        examples(args.examples, device)


if __name__ == "__main__":
    main()
