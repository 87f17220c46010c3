"""Peers timed side by side: tnf's warp simulator, TACTO and Taxim, in one run on this machine.

    nox -s peers                                   # CPU: makes TACTO's environment, then runs this script
    python bench/peers.py --tacto-python .nox/peers/bin/python --out results/sim/peers_cpu.md
    python bench/peers.py --device cuda --maps 256 --taxim-batch 256 --out results/sim/peers_cuda_h200.md   # a GPU

Two workloads, each run by every simulator that takes it:

- **Objects, Digit** (tnf and TACTO) at 120x160 and 240x320: the builtin objects of bench/sim.py and an icosphere,
  pressed with 1-8 N from poses around each. tnf presses them (ray cast, force solve, deformation, shading, blur,
  noise). TACTO renders the same objects at tnf's contact poses, mapped into its sensor frame, with the same
  forces: per frame what its ``Sensor.render`` does after PyBullet reports the contact (bench/peers_tacto.py).
- **Height maps, GelSight Mini** (tnf and Taxim) at Taxim's 640x480: spheres of 135 pixels' radius at random
  centres, pressed 0.3-1.0 mm (in Taxim's 0.0295 mm pixels; tnf gets the same maps in its own pixel pitch). tnf
  presses them with ``press_heights`` (its uncalibrated optics); Taxim renders them with its own GelSight Mini
  calibration, with and without its shadows, through its JAX backend (one frame per call) and its torch backend
  (``--taxim-batch`` frames per call, on the GPU when tnf runs there). Both tnf and Taxim's torch backend take the
  maps from host memory and return the images to it, inside the timing.

Taxim's torch backend imports torch-scatter, which PyPI ships as source only. Where it is not installed,
bench/peers_scatter.py stands in for its one function (``scatter_min``, by torch's ``scatter_reduce``) and the
rows say so. On a GPU, TACTO's environment is there only if made with ``nox -s peers`` (its EGL rendering could
then use the GPU), and Taxim's JAX backend runs on the GPU only with a CUDA build of jaxlib (with the CPU build its
rows say ``cpu``).

TACTO pins old numpy and pyrender: it runs in a separate interpreter (``--tacto-python``, the environment that
``nox -s peers`` makes) as a subprocess of this run, on the same machine, right after tnf. Every simulator runs
``--runs`` times after a warm-up; the table gives the best and the median wall-clock milliseconds per frame and the
ratios of the best. Threads: tnf's warp CPU kernels use one core; TACTO's pyrender (Mesa llvmpipe) and Taxim's XLA
use the cores they find.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("WARP_CACHE_PATH", str(Path(__file__).resolve().parents[1] / ".warp-cache"))
# JAX takes 75 % of a GPU's memory at its first use; Taxim's torch backend runs after it in this process.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import numpy as np  # noqa: E402
from peers_scatter import install as install_scatter  # noqa: E402
from sim import workload  # noqa: E402  (bench/sim.py: the same objects and start poses)

from tnf.registry import SENSORS, SIMULATORS  # noqa: E402
from tnf.runtime import environment, init_warp  # noqa: E402

DIGIT_SIZES = ((120, 160), (240, 320))  # width, height
TAXIM_PIXEL_MM = 0.0295  # Taxim's GelSight Mini calibration: gel size of one pixel
BALL_PX = 135.0  # radius of the pressed sphere in pixels (4 mm in Taxim's pixels)
# TACTO's Digit (tacto/config_digit.yml): camera at (0, 0, 0.015) looking along +x, gel 0.022 m in front of it.
TACTO_GEL_X, TACTO_CAMERA_Z = 0.022, 0.015


def timed(fn, runs: int) -> tuple[list[float], list[float]]:
    """Wall-clock and CPU seconds of ``runs`` calls of ``fn`` (after the caller's warm-up)."""
    walls, cpus = [], []
    for run in range(runs):
        t0, c0 = time.perf_counter(), time.process_time()
        fn(run)
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return walls, cpus


def tnf_objects(device: str, size: tuple[int, int], work, forces: np.ndarray, runs: int) -> dict:
    """tnf's ms per Digit frame on the objects, and each object's contact poses (sensor to world) and forces."""
    import warp as wp

    sensor = SENSORS.build({"name": "digit", "width": size[0], "height": size[1]})
    sim = SIMULATORS.build({"name": "warp_gel"}, sensor=sensor, device=device)
    contacts = {}
    for name, mesh, c2w in work:  # warm-up: compile, build the BVHs; keep the contact poses for TACTO
        r = sim.press(mesh, c2w, forces)
        contacts[name] = (r.contact_c2w, r.force, r.penetration)
    wp.synchronize_device(device)

    def once(run: int) -> None:
        for i, (_, mesh, c2w) in enumerate(work):
            sim.press(mesh, c2w, forces, seed=run * 100 + i, host=False)
        wp.synchronize_device(device)

    walls, cpus = timed(once, runs)
    frames = sum(len(c2w) for _, _, c2w in work)
    touching = float(np.mean(np.concatenate([p for _, _, p in contacts.values()]) > 0))
    return {
        "wall_ms": [1e3 * w / frames for w in walls],
        "cpu_ms": [1e3 * c / frames for c in cpus],
        "touching": touching,
        "contacts": contacts,
    }


def tacto_poses(contact_c2w: np.ndarray, gel_centre: float) -> np.ndarray:
    """Object poses ``[B, 4, 4]`` in TACTO's sensor frame from tnf's contact poses (sensor to world, OpenGL camera
    looking along -z, the undeformed gel's centre ``gel_centre`` metres in front): tnf's -z becomes TACTO's +x,
    +y its +z, +x its -y, and the centres of the two undeformed gels coincide."""
    m = np.eye(4)
    m[:3, :3] = [[0, 0, -1], [-1, 0, 0], [0, 1, 0]]
    m[:3, 3] = [TACTO_GEL_X - gel_centre, 0.0, TACTO_CAMERA_Z]
    return np.einsum("ij,bjk->bik", m, np.linalg.inv(np.asarray(contact_c2w, np.float64)))


def tacto_objects(python: str, work, contacts: dict, forces: np.ndarray, poses: int, runs: int) -> dict:
    """TACTO's result (bench/peers_tacto.py) on the same objects, contact poses and forces, per Digit size."""
    sensor = SENSORS.build({"name": "digit"})
    sag = sensor.gel_surface()
    gel_centre = sensor.cfg.camera_distance + float(sag[sag.shape[0] // 2, sag.shape[1] // 2])
    with tempfile.TemporaryDirectory() as tmp:
        arrays: dict[str, np.ndarray] = {
            "names": np.array([name for name, _, _ in work]),
            "forces": np.asarray(forces[:poses], np.float64),
            "sizes": np.array(DIGIT_SIZES),
            "runs": np.array(runs),
        }
        for name, mesh, _ in work:
            arrays[f"{name}_vertices"] = np.asarray(mesh.vertices, np.float64)
            arrays[f"{name}_faces"] = np.asarray(mesh.faces, np.int64)
            arrays[f"{name}_poses"] = tacto_poses(contacts[name][0][:poses], gel_centre)
        np.savez(Path(tmp) / "work.npz", **arrays)
        script = Path(__file__).with_name("peers_tacto.py")
        env = {**os.environ, "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "egl")}
        run = subprocess.run(
            [python, str(script), str(Path(tmp) / "work.npz"), str(Path(tmp) / "out.json")],
            env=env,
            capture_output=True,
            text=True,
        )
        if run.returncode != 0:
            raise SystemExit(f"TACTO's run failed:\n{run.stderr[-3000:]}")
        return json.loads((Path(tmp) / "out.json").read_text())


def ball_maps(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Centres ``[n, 2]`` (column, row; pixels of a 640x480 frame) and press depths ``[n]`` (Taxim's mm)."""
    rng = np.random.default_rng(seed)
    centres = np.stack([rng.uniform(200, 440, n), rng.uniform(150, 330, n)], axis=1)
    return centres, rng.uniform(0.3, 1.0, n)


def tnf_maps(device: str, centres: np.ndarray, depths_mm: np.ndarray, runs: int) -> dict:
    """tnf's ms per GelSight Mini frame at 640x480 on the sphere height maps (``press_heights``)."""
    import warp as wp

    from tnf.real.presses import sphere_gaps

    sensor = SENSORS.build({"name": "gelsight_mini", "width": 640, "height": 480})
    sim = SIMULATORS.build({"name": "warp_gel"}, sensor=sensor, device=device)
    fx = sensor.intrinsics()[0]
    pitch_m = sensor.cfg.camera_distance / fx  # metres of gel per pixel
    scale = pitch_m / (TAXIM_PIXEL_MM * 1e-3)  # the same map in tnf's pixels
    gaps = sphere_gaps(sensor, centres, BALL_PX * pitch_m)
    depths = depths_mm * 1e-3 * scale
    sim.press_heights(gaps[:2], penetration=depths[:2])  # warm-up
    wp.synchronize_device(device)
    walls, cpus = timed(lambda run: sim.press_heights(gaps, penetration=depths, seed=run), runs)
    return {"wall_ms": [1e3 * w / len(gaps) for w in walls], "cpu_ms": [1e3 * c / len(gaps) for c in cpus]}


def taxim_maps(
    backend: str, device: str, centres: np.ndarray, depths_mm: np.ndarray, runs: int, with_shadow: bool, batch: int
) -> dict:
    """Taxim's ms per GelSight Mini frame at 640x480 on the same sphere height maps, host arrays in and out.

    ``backend="jax"`` renders one frame per call (its render takes one press depth). ``backend="torch"`` renders
    ``batch`` frames per call on ``device``: each map is shifted to its press depth first, as Taxim's own
    ``press_depth`` does, inside the timed loop.
    """
    from taxim import CALIB_GELSIGHT_MINI, Taxim

    sim = Taxim(calib_folder=CALIB_GELSIGHT_MINI, backend=backend, **({"device": device} if backend == "torch" else {}))
    rows, cols = np.mgrid[: sim.height, : sim.width]
    r = BALL_PX * TAXIM_PIXEL_MM

    def height_map(c: np.ndarray) -> np.ndarray:
        d2 = ((cols - c[0]) ** 2 + (rows - c[1]) ** 2) * TAXIM_PIXEL_MM**2
        return np.where(d2 < r * r, r - np.sqrt(np.maximum(r * r - d2, 0.0)), 10.0 * r).astype(np.float32)

    maps = np.stack([height_map(c) for c in centres])
    if backend == "jax":
        np.asarray(sim.render(maps[0], with_shadow=with_shadow, press_depth=float(depths_mm[0])))  # compile

        def once(run: int) -> None:
            for z, d in zip(maps, depths_mm, strict=True):
                np.asarray(sim.render(z, with_shadow=with_shadow, press_depth=float(d)))

    else:
        import torch

        def once(run: int) -> None:
            for b0 in range(0, len(maps), batch):
                z = torch.from_numpy(maps[b0 : b0 + batch]).to(device)
                d = torch.from_numpy(depths_mm[b0 : b0 + batch].astype(np.float32)).to(device)
                z = z - z.amin(dim=(-2, -1), keepdim=True) - d[:, None, None]
                sim.render(z, with_shadow=with_shadow).cpu().numpy()

        once(-1)  # warm-up: kernels, caches of the background at this size
    walls, cpus = timed(once, runs)
    return {"wall_ms": [1e3 * w / len(maps) for w in walls], "cpu_ms": [1e3 * c / len(maps) for c in cpus]}


def positive(text: str) -> int:
    """argparse type: a whole number >= 1."""
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return int(text)


def row(workload: str, size: str, name: str, r: dict, ref: dict | None, note: str = "") -> str:
    best, median = min(r["wall_ms"]), statistics.median(r["wall_ms"])
    ratio = f"{min(r['wall_ms']) / min(ref['wall_ms']):.1f}x" if ref is not None else "1.0x"
    cpu = min(r["cpu_ms"])
    cells = [workload, size, name, f"{best:.2f}", f"{median:.2f}", f"{cpu:.2f}", f"{1e3 / best:,.0f}", ratio, note]
    return "| " + " | ".join(cells) + " |"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", help="tnf's device: cpu, cuda, cuda:N")
    ap.add_argument("--batch", type=int, default=None, help="tnf's touches per launch (default: 16 cpu, 512 cuda)")
    ap.add_argument("--poses", type=int, default=16, help="poses per object that TACTO renders (tnf's first ones)")
    ap.add_argument("--maps", type=int, default=16, help="sphere height maps (tnf and Taxim)")
    ap.add_argument("--runs", type=int, default=3, help="timed runs of each simulator")
    ap.add_argument(
        "--tacto-python",
        default=os.environ.get("TNF_PEERS_PYTHON"),
        help="the interpreter of TACTO's environment (nox -s peers makes it); TACTO is skipped without it",
    )
    ap.add_argument("--taxim-batch", type=positive, default=16, help="height maps per call of Taxim's torch backend")
    ap.add_argument("--no-taxim", action="store_true", help="skip Taxim")
    ap.add_argument("--out", type=Path, default=None, help="also write the table as markdown here")
    args = ap.parse_args()
    device = "cuda:0" if args.device == "cuda" else args.device
    init_warp()
    gpu = device.startswith("cuda")
    batch = args.batch or (512 if gpu else 16)
    env = environment(device)
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    machine = f"{env.get('accelerator')}, {cores} CPU cores, load average {load} at the start"
    print(f"machine: {machine}", flush=True)
    lines = [
        "| workload | size (w x h) | simulator | best ms/frame | median ms/frame | CPU ms/frame | frames/s "
        "| time vs tnf | notes |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    skipped: list[str] = []

    work = workload(batch)
    forces = np.linspace(1.0, 8.0, batch)
    ours: dict[tuple[int, int], dict] = {}
    for size in DIGIT_SIZES:
        ours[size] = tnf_objects(device, size, work, forces, args.runs)
        note = f"batch {batch}; {100 * ours[size]['touching']:.0f} % of frames in contact"
        lines.append(row("objects, Digit", f"{size[0]}x{size[1]}", f"tnf ({device})", ours[size], None, note))
        print(lines[-1], flush=True)
    if args.tacto_python:
        poses = min(args.poses, batch)
        tacto = tacto_objects(args.tacto_python, work, ours[DIGIT_SIZES[-1]]["contacts"], forces, poses, args.runs)
        for t in tacto["sizes"]:
            size = (t["width"], t["height"])
            note = f"{poses} poses per object; {100 * t['touching']:.0f} % of frames dent the gel"
            lines.append(row("objects, Digit", f"{size[0]}x{size[1]}", "TACTO (CPU)", t, ours[size], note))
            print(lines[-1], flush=True)
    else:
        skipped.append("TACTO: no --tacto-python (its environment: nox -s peers)")

    centres, depths = ball_maps(args.maps)
    mine = tnf_maps(device, centres, depths, args.runs)
    note = f"{args.maps} sphere presses, press_heights, uncalibrated optics"
    lines.append(row("height maps, GelSight Mini", "640x480", f"tnf ({device})", mine, None, note))
    print(lines[-1], flush=True)
    if args.no_taxim:
        skipped.append("Taxim: --no-taxim")
    else:
        for backend in ("jax", "torch"):
            try:
                if backend == "jax":
                    import jax

                    where, per_call = jax.default_backend(), "one frame per call"
                else:
                    import torch

                    try:
                        import torchvision  # noqa: F401  (Taxim's torch backend resizes with it)
                    except RuntimeError as e:  # a torchvision built for another torch
                        raise ImportError(f"torchvision does not load with torch {torch.__version__}: {e}") from e
                    scatter = install_scatter()
                    where = device if gpu and torch.cuda.is_available() else "cpu"
                    per_call = f"{args.taxim_batch} frames per call; torch {torch.__version__}"
                    if scatter == "scatter_reduce":
                        per_call += "; torch-scatter's scatter_min by torch's scatter_reduce (bench/peers_scatter.py)"
                for shadow in (True, False):
                    t = taxim_maps(backend, where, centres, depths, args.runs, shadow, args.taxim_batch)
                    label = "JAX" if backend == "jax" else "torch"
                    name = f"Taxim {label} ({where})" + ("" if shadow else ", no shadows")
                    lines.append(row("height maps, GelSight Mini", "640x480", name, t, mine, per_call))
                    print(lines[-1], flush=True)
            except ImportError as e:
                skipped.append(f"Taxim {backend}: {e}")
    here = Path.cwd()
    shown = [
        os.path.relpath(a, here) if Path(a).is_absolute() and Path(a).is_relative_to(here) else a for a in sys.argv
    ]
    command = "python bench/peers.py " + " ".join(shown[1:])
    head = [
        "# Peers timed side by side",
        "",
        f"Machine: {machine}. Command: `{command}` (`nox -s peers` runs it with TACTO's environment).",
        "",
        "ms/frame: wall clock, best and median of the runs. CPU ms/frame: this process's CPU time (TACTO's: its",
        "process's, Mesa's threads included), best run. Time vs tnf: the best wall time over tnf's on the same",
        "workload. The workloads, and what each simulator does per frame: the docstring of bench/peers.py.",
        "",
    ]
    report = "\n".join([*head, *lines, ""])
    if skipped:
        report += "\nNot run: " + "; ".join(skipped) + ".\n"
        print("not run: " + "; ".join(skipped))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(report)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    sys.exit(main())
