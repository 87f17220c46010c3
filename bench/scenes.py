"""Benchmark of scene fitting: quality (PSNR, SSIM, depth error), training time, render speed, peak memory.

Fits one object and prints its figures. The object is the analytic test sphere (rendered exactly in NumPy,
no renderer needed) or, with ``--object NAME``, a built-in object captured with ``tnf capture``'s renderer.

    python bench/scenes.py --device cuda --scene hashgrid --steps 3000 --out bench-out
    python bench/scenes.py --device cpu --scene hashgrid --steps 200 --size 32 --views 12 --tiny

Writes ``<out>/<object>/`` (the dataset), ``<out>/<scene>-<object>/`` (scene.pt, metrics.json, preview.png)
and ``<out>/<scene>-<object>.json`` (the figures printed). No network access is needed.

Fitting K objects together (``fit.batch_objects``, ``tnf.scenes.batched``) against one after another, on one
device: steps/s and held-out PSNR per object for both (K analytic spheres of other sizes, or ``--objects``):

    python bench/scenes.py --device cuda --batched 27 --steps 3000 --size 256 --views 48 --out bench-batched
    python bench/scenes.py --device cpu --batched 3 --steps 60 --size 24 --views 10 --tiny --eval-every 0

Where a batched step spends its time (the top operators of a short fit together; ``--separate skip``):

    python bench/scenes.py --device cuda --batched 27 --steps 200 --size 256 --views 48 --separate skip --profile

The same fit with the hash encoding and its table gradient by Warp kernels (``--train-kernel``), to compare its
seconds and held-out PSNR with the line above's:

    python bench/scenes.py --device cuda --batched 27 --steps 200 --size 256 --views 48 --separate skip --train-kernel

The separate fits as a sweep of ``tnf fit-scene`` jobs sharing the device (W processes; the pool's wall time):

    python bench/scenes.py --device cuda --batched 27 --steps 3000 --size 256 --views 48 --separate lightning \
        --workers 6 --no-together --out bench-sweep

Rendering only, of a scene fitted before (frames/s at 128 x 128 for batches of 64 poses, peak memory,
samples per ray, and the difference to the dense quadrature over every sample):

    python bench/scenes.py --device cuda --load bench-out/hashgrid-sphere
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

TINY_HASHGRID = {
    "levels": 4,
    "log2_table_size": 14,
    "base_resolution": 8,
    "max_resolution": 64,
    "hidden": 32,
    "samples_per_ray": 64,
    "occupancy_resolution": 16,
    "occupancy_update_every": 8,
    "occupancy_warmup": 16,
}
TINY_NERF = {"depth": 4, "width": 64, "skip": 2, "samples_coarse": 32, "samples_fine": 32}


def make_dataset(args: argparse.Namespace, folder: Path, name: str | None = None) -> tuple[Path, float | None]:
    """The capture folder of the object ``name`` (default ``args.object``; made if missing) and its size in
    metres. ``sphere`` is the analytic sphere, ``sphere-N`` one of other sizes seen from other distances."""
    name = name or args.object
    if name == "sphere" or name.startswith("sphere-"):
        from tnf.scenes.synthetic import write_sphere_dataset

        # sphere-N: radius 3.5 to 6.5 cm, cameras 3.2 to 5.2 radii away (other bounds and step sizes).
        n = int(name.split("-")[1]) if "-" in name else None
        radius = 0.05 if n is None else 0.035 + 0.03 * ((n * 0.618) % 1.0)
        distance = 0.2 if n is None else radius * (3.2 + 2.0 * ((n * 0.382) % 1.0))
        if not (folder / "transforms.json").is_file():
            write_sphere_dataset(folder, args.views, args.test_views, args.size, radius=radius, distance=distance)
        return folder, 2 * radius
    # A built-in object through the capture stage's own renderer (needs pyrender with EGL).
    from tnf.env import headless_rendering

    headless_rendering()
    import numpy as np

    from tnf.capture import camera_poses, capture_config, intrinsics, write_views
    from tnf.capture.render import MeshRenderer
    from tnf.registry import OBJECTS

    mesh = OBJECTS.build({"name": "builtin"}).load(name)
    ccfg = capture_config({"resolution": args.size, "num_views": args.views, "num_test_views": args.test_views})
    if not (folder / "transforms.json").is_file():
        radius = float(np.linalg.norm(mesh.vertices, axis=1).max())
        train, test = camera_poses(radius, ccfg, seed=0)
        renderer = MeshRenderer(mesh, args.size, args.size, ccfg.background, ccfg.ambient, ccfg.light_intensity)
        k = intrinsics(ccfg)
        try:
            folder.mkdir(parents=True, exist_ok=True)
            write_views(folder, "train", train, *renderer.render(train, k), ccfg)
            write_views(folder, "test", test, *renderer.render(test, k), ccfg)
        finally:
            renderer.close()
    return folder, float(max(mesh.extents))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", help="cpu or cuda")
    ap.add_argument("--scene", default="hashgrid", choices=["hashgrid", "nerf"])
    ap.add_argument("--steps", type=int, default=None, help="training steps (default: the kind's default)")
    ap.add_argument("--batch-rays", type=int, default=None, help="rays per step (default: the kind's default)")
    ap.add_argument("--lr", type=float, default=None)
    ap.add_argument("--object", default="sphere", help="'sphere' (analytic) or a built-in object name")
    ap.add_argument("--size", type=int, default=128, help="image size in pixels")
    ap.add_argument("--views", type=int, default=48, help="training views")
    ap.add_argument("--test-views", type=int, default=8)
    ap.add_argument("--tiny", action="store_true", help="the small CPU configuration of debug/tiny")
    ap.add_argument("--set", nargs="*", default=[], help="scene config overrides key=value (JSON values)")
    ap.add_argument("--render-views", type=int, default=64, help="views per render batch for frames/s")
    ap.add_argument("--render-size", type=int, default=128, help="rendered frame size for frames/s")
    ap.add_argument("--chunk", type=int, default=None, help="rays per render chunk (default: the kind's)")
    ap.add_argument("--objects-in-paper", type=int, default=27)
    ap.add_argument("--out", default="bench-scenes", help="output folder")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--eval-every", type=int, default=250, help="steps between test-PSNR checks (0: none)")
    ap.add_argument("--load", default=None, help="a fitted scene (folder or scene.pt): measure rendering only")
    ap.add_argument("--half", choices=["auto", "on", "off"], default="auto", help="float16 rendering (auto: CUDA)")
    ap.add_argument("--compile", action="store_true", help="torch.compile the hash grid's rendering field")
    ap.add_argument("--march-kernel", choices=["auto", "on", "off"], default="auto", help="Warp march selection")
    ap.add_argument("--distortion-weight", type=float, default=None, help="fit.distortion_weight (default: fit's)")
    ap.add_argument(
        "--profile",
        action="store_true",
        help="with --load: print the top operators of one batch; with --batched: of the whole fit together "
        "(give few --steps)",
    )
    ap.add_argument("--batched", type=int, default=0, help="fit K objects together and one after another: compare")
    ap.add_argument("--objects", default=None, help="with --batched: comma-separated built-in objects (else spheres)")
    ap.add_argument(
        "--separate",
        choices=["auto", "lightning", "loop", "skip"],
        default="auto",
        help="with --batched, how the objects are fitted one after another: fit_scene (Lightning, as tnf "
        "fit-scene), the batched loop with one object, or not at all (auto: Lightning where installed)",
    )
    ap.add_argument("--workers", type=int, default=1, help="with --separate lightning: fit in this many processes")
    ap.add_argument("--no-together", action="store_true", help="with --batched: the separate fits only")
    ap.add_argument(
        "--train-kernel", action="store_true",
        help="train the hash encoding by Warp kernels (fit.train_kernel)",
    )  # fmt: skip
    args = ap.parse_args()
    if args.load:
        render_only(args)
        return
    if args.batched:
        batched_bench(args)
        return

    import torch
    from PIL import Image

    from tnf.cameras import read_views
    from tnf.scenes import save_scene
    from tnf.scenes.fit import build_scene, evaluate_scene, fit_scene, preview_strip
    from tnf.scenes.system import FitSettings

    if args.device.startswith("cuda"):
        torch.backends.cuda.matmul.allow_tf32 = True
    out = Path(args.out)
    data, size = make_dataset(args, out / args.object)
    params = dict(TINY_HASHGRID if args.scene == "hashgrid" else TINY_NERF) if args.tiny else {}
    for kv in args.set:
        k, v = kv.split("=", 1)
        params[k] = json.loads(v)
    extra = {"train_kernel": args.train_kernel}
    if args.distortion_weight is not None:
        extra["distortion_weight"] = args.distortion_weight
    settings = FitSettings(steps=args.steps, batch_rays=args.batch_rays, lr=args.lr, chunk=args.chunk, **extra)
    run_dir = out / f"{args.scene}-{args.object}"
    run_dir.mkdir(parents=True, exist_ok=True)
    train, test = read_views(data / "transforms.json"), read_views(data / "transforms_test.json")
    torch.manual_seed(args.seed)
    scene = build_scene({"name": args.scene, **params}, train)
    if args.device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    # PSNR on the test views every eval_every steps; the evaluation time is not training time.
    curve: list[dict] = []
    excluded = [0.0]
    t_start = time.perf_counter()

    def on_step(step: int, loss: float) -> None:
        if not args.eval_every or (step + 1) % args.eval_every:
            return
        _sync(args.device)
        t = time.perf_counter()
        ev = evaluate_scene(scene, test, settings.chunk, size)["metrics"]
        scene.train()
        curve.append({"step": step + 1, "seconds": round(t - t_start - excluded[0], 2), "psnr": round(ev["psnr"], 2)})
        print(f"step {step + 1}: {curve[-1]['seconds']} s, test PSNR {curve[-1]['psnr']} dB", flush=True)
        excluded[0] += time.perf_counter() - t

    info = fit_scene(scene, train, settings, args.scene, args.device, on_step=on_step, seed=args.seed)
    train_seconds = info["train_seconds"] - excluded[0]
    fit_peak = torch.cuda.max_memory_allocated() / 2**30 if args.device.startswith("cuda") else None
    ev = evaluate_scene(scene, test, settings.chunk, size)
    metrics = {**ev["metrics"], "steps": info["steps"], "train_seconds": train_seconds}
    Image.fromarray(preview_strip(ev["gt"], ev["rgb"], ev["depth"], 4)).save(run_dir / "preview.png")
    save_scene(scene, run_dir)
    hit = [c for c in curve if c["psnr"] >= 30.0]

    scene = load_scene_for_rendering(run_dir, args)
    speed = measure_rendering(scene, args)
    import resource

    figures = {
        "scene": args.scene,
        "object": args.object,
        "device": torch.cuda.get_device_name() if args.device.startswith("cuda") else "cpu",
        "size_px": args.size,
        "train_views": args.views,
        "steps": metrics["steps"],
        "train_seconds": round(metrics["train_seconds"], 2),
        "seconds_to_30db": hit[0]["seconds"] if hit else None,
        "psnr_curve": curve,
        "psnr_db": round(metrics.get("psnr", float("nan")), 2),
        "ssim": round(metrics.get("ssim", float("nan")), 4),
        "depth_error_median_m": metrics.get("depth_error_median_m"),
        "depth_error_rel_object_size": metrics.get("depth_error_median_rel"),
        **speed,
        "peak_gpu_memory_fit_gib": fit_peak,
        "peak_cpu_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
        f"train_seconds_for_{args.objects_in_paper}_objects": round(metrics["train_seconds"] * args.objects_in_paper),
        "distortion_weight": settings.distortion_weight,
        "scene_config": params,
    }
    (out / f"{args.scene}-{args.object}.json").write_text(json.dumps(figures, indent=2) + "\n")
    for key, value in figures.items():
        print(f"{key:>36}: {value}")


def _new_scene(params: dict, views, settings, seed: int):
    """A hash grid of ``params`` for the training ``views``, seeded and carved as ``tnf fit-scene`` makes one."""
    import torch

    from tnf.scenes.fit import build_scene

    torch.manual_seed(seed)
    s = build_scene({"name": "hashgrid", **params}, views)
    if settings.carve:
        s.carve(*views.cameras(), views.rgba()[..., 3])
    return s


def _psnr(scene, views, settings, size: float | None) -> float:
    """Held-out PSNR (dB) of ``scene`` on the test ``views``."""
    import importlib.util

    from tnf.scenes.fit import evaluate_scene

    if importlib.util.find_spec("warp") is None:
        scene.render_kernel = False  # render with the PyTorch encoding where Warp is not installed
    return round(evaluate_scene(scene, views, settings.chunk, size)["metrics"]["psnr"], 2)


def _fit_alone(folder: str, params: dict, settings, device: str, seed: int, size: float | None) -> tuple[float, float]:
    """One object fitted alone through ``fit_scene`` (as ``tnf fit-scene``): its training seconds and held-out
    PSNR. Runs in a worker process of ``--workers``."""
    import torch

    from tnf.cameras import read_views
    from tnf.scenes.fit import fit_scene

    if device.startswith("cuda"):
        torch.backends.cuda.matmul.allow_tf32 = True
    train, test = read_views(Path(folder) / "transforms.json"), read_views(Path(folder) / "transforms_test.json")
    s = _new_scene(params, train, settings, seed)
    info = fit_scene(s, train, settings, "hashgrid", device, seed=seed)
    return info["train_seconds"], _psnr(s, test, settings, size)


def batched_bench(args: argparse.Namespace) -> None:
    """``--batched K``: fit K objects one after another and then together on ``args.device`` with the same
    seed and settings; print each object's held-out PSNR both ways and the training steps/s of both."""
    import importlib.util
    import resource

    import torch

    from tnf.cameras import read_views
    from tnf.scenes.batched import fit_batched
    from tnf.scenes.settings import FitSettings

    if args.scene != "hashgrid":
        raise SystemExit("--batched fits hash grids only")
    separate = args.separate
    if separate == "auto":
        separate = "lightning" if importlib.util.find_spec("lightning") else "loop"
    if args.workers < 1 or (args.workers > 1 and separate != "lightning"):
        raise SystemExit(f"--workers {args.workers}: give 1, or more with --separate lightning (got {separate})")
    if args.no_together and separate == "skip":
        raise SystemExit("--no-together with --separate skip leaves nothing to fit")
    if args.device.startswith("cuda"):
        torch.backends.cuda.matmul.allow_tf32 = True
    K, out = args.batched, Path(args.out)
    names = args.objects.split(",") if args.objects else [f"sphere-{k}" for k in range(K)]
    if len(names) != K:
        raise SystemExit(f"--objects names {len(names)} objects, --batched asks for {K}")
    data = [make_dataset(args, out / name, name) for name in names]
    params = dict(TINY_HASHGRID) if args.tiny else {}
    for kv in args.set:
        k, v = kv.split("=", 1)
        params[k] = json.loads(v)
    extra = {"train_kernel": args.train_kernel}
    if args.distortion_weight is not None:
        extra["distortion_weight"] = args.distortion_weight
    settings = FitSettings(steps=args.steps, batch_rays=args.batch_rays, lr=args.lr, chunk=args.chunk, **extra)
    settings = settings.resolved("hashgrid")
    trains = [read_views(folder / "transforms.json") for folder, _ in data]
    tests = [read_views(folder / "transforms_test.json") for folder, _ in data]

    def scene(k: int):
        return _new_scene(params, trains[k], settings, args.seed)

    def psnr(s, k: int) -> float:
        s.march_kernel = {"auto": None, "on": True, "off": False}[args.march_kernel]
        return _psnr(s, tests[k], settings, data[k][1])

    # Warm-up (CUDA context, kernels, allocator) before anything is timed: a few steps of the batched loop.
    warm = FitSettings(**{**settings.__dict__, "steps": 3})
    fit_batched([scene(0)], trains[:1], warm, args.device, seed=args.seed)
    rows = [{"object": n, "bound_m": None} for n in names]
    alone_seconds = alone_wall = None
    if separate == "lightning" and args.workers > 1:
        # As a sweep of `tnf fit-scene` jobs sharing the device: W processes, each fitting its share in turn. The
        # figure is the wall time of the whole pool, the processes' start-up included.
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        t0 = time.perf_counter()
        with ProcessPoolExecutor(args.workers, mp_context=mp.get_context("spawn")) as pool:
            jobs = [
                pool.submit(_fit_alone, str(data[k][0]), params, settings, args.device, args.seed, data[k][1])
                for k in range(K)
            ]
            done = [j.result() for j in jobs]
        alone_wall = time.perf_counter() - t0
        alone_seconds = sum(d[0] for d in done)
        for k, (_, p) in enumerate(done):
            rows[k]["psnr_alone_db"] = p
        print(f"alone, {args.workers} workers: {alone_wall:.1f} s wall ({alone_seconds:.1f} s of training)")
    elif separate != "skip":
        alone_seconds = 0.0
        for k in range(K):
            s = scene(k)
            if separate == "lightning":
                from tnf.scenes.fit import fit_scene

                info = fit_scene(s, trains[k], settings, "hashgrid", args.device, seed=args.seed)
            else:
                info = fit_batched([s], trains[k : k + 1], settings, args.device, seed=args.seed)[0]
            alone_seconds += info["train_seconds"]
            rows[k]["psnr_alone_db"] = psnr(s, k)
            print(f"alone {names[k]}: {info['train_seconds']:.1f} s, PSNR {rows[k]['psnr_alone_db']} dB", flush=True)
    if args.device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    steps = settings.steps
    assert steps is not None
    together_seconds = peak = None
    phases: dict[str, float] = {}
    if not args.no_together:
        scenes = [scene(k) for k in range(K)]
        # Seconds per step before and after the occupancy grid's warm-up (the grid is the carved hull until then,
        # so those steps render many more samples): a short run's mix of the two is not a full fit's.
        warmup, marks = scenes[0].cfg.occupancy_warmup, {}

        def mark(step: int, loss: float) -> None:
            if step in (0, warmup - 1, steps - 1):
                if args.device.startswith("cuda"):
                    torch.cuda.synchronize()
                marks[step] = time.perf_counter()

        with _profiled(args.profile, args.device):
            infos = fit_batched(scenes, trains, settings, args.device, seed=args.seed, on_step=mark)
        together_seconds = infos[0]["train_seconds"]
        print(f"together: {together_seconds:.1f} s", flush=True)
        if 1 < warmup < steps - 1:
            before = (marks[warmup - 1] - marks[0]) / (warmup - 1)
            after = (marks[steps - 1] - marks[warmup - 1]) / (steps - warmup)
            phases = {"ms_per_step_warmup": round(1e3 * before, 1), "ms_per_step_after": round(1e3 * after, 1)}
            print(f"per step: {phases['ms_per_step_warmup']} ms in the {warmup} warm-up steps, "
                  f"{phases['ms_per_step_after']} ms after them", flush=True)  # fmt: skip
        peak = torch.cuda.max_memory_allocated() / 2**30 if args.device.startswith("cuda") else None
        for k, s in enumerate(scenes):
            rows[k]["bound_m"] = round(s.bound, 4)
            rows[k]["psnr_together_db"] = psnr(s, k)
    figures = {
        "device": torch.cuda.get_device_name() if args.device.startswith("cuda") else "cpu",
        "objects": K,
        "steps": steps,
        "batch_rays": settings.batch_rays,
        "size_px": args.size,
        "train_views": args.views,
        "separate": separate,
        "workers": args.workers,
        "alone_train_seconds": round(alone_seconds, 2) if alone_seconds is not None else None,
        "alone_wall_seconds": round(alone_wall, 2) if alone_wall is not None else None,
        "alone_object_steps_per_s": round(K * steps / alone_seconds, 1) if alone_seconds else None,
        "together_train_seconds": round(together_seconds, 2) if together_seconds else None,
        "together_steps_per_s": round(steps / together_seconds, 2) if together_seconds else None,
        "together_object_steps_per_s": round(K * steps / together_seconds, 1) if together_seconds else None,
        "speed_up": round(alone_seconds / together_seconds, 2) if alone_seconds and together_seconds else None,
        **phases,
        "peak_gpu_memory_together_gib": round(peak, 2) if peak is not None else None,
        "peak_cpu_rss_gib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 2),
        "scene_config": params,
        "per_object": rows,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / f"batched-{K}.json").write_text(json.dumps(figures, indent=2) + "\n")
    print(f"{'object':>16} {'bound m':>8} {'PSNR alone':>11} {'PSNR together':>14}")
    for r in rows:
        bound, together = r["bound_m"] or "", r.get("psnr_together_db", "")
        print(f"{r['object']:>16} {bound:>8} {r.get('psnr_alone_db', ''):>11} {together:>14}")
    for key, value in figures.items():
        if key != "per_object":
            print(f"{key:>36}: {value}")


@contextlib.contextmanager
def _profiled(on: bool, device: str):
    """With ``on``, profile the block and print its top 25 operators by their own time on ``device`` (the
    profiler's overhead inflates the timed seconds: read the shares, not the total)."""
    if not on:
        yield
        return
    from torch.profiler import ProfilerActivity, profile

    cuda = device.startswith("cuda")
    acts = [ProfilerActivity.CPU, ProfilerActivity.CUDA] if cuda else [ProfilerActivity.CPU]
    with profile(activities=acts) as prof:
        yield
    key = "self_cuda_time_total" if cuda else "self_cpu_time_total"
    print(prof.key_averages().table(sort_by=key, row_limit=25), flush=True)


def load_scene_for_rendering(path: str | Path, args: argparse.Namespace):
    """The fitted scene at ``path`` on ``args.device`` with the rendering options of ``args``."""
    from tnf.scenes import load_scene

    scene = load_scene(path, args.device)
    if hasattr(scene, "render_half"):
        scene.render_half = {"auto": None, "on": True, "off": False}[args.half]
        scene.render_compile = args.compile
        scene.march_kernel = {"auto": None, "on": True, "off": False}[args.march_kernel]
    return scene


def render_cameras(scene, n: int, size: int):
    """``n`` camera poses around the object (2.2 bounds away) and the intrinsics of a 40-degree view at
    ``size`` px: the frames every rendering figure is measured on."""
    import torch

    from tnf.scenes.synthetic import sphere_poses

    c2w = torch.tensor(sphere_poses(n, 2.2 * scene.bound, offset=0.123), dtype=torch.float32)
    f = 0.5 * size / torch.tan(torch.tensor(0.5 * 0.7))
    return c2w, torch.tensor([f, f, size / 2, size / 2])


def measure_rendering(scene, args: argparse.Namespace) -> dict:
    """Frames/s of batches of ``render_views`` poses at ``render_size`` px around the object, peak memory,
    the march's counts per ray, and how far the renders are from the dense quadrature (every sample)."""
    import torch

    from tnf.cameras import camera_rays
    from tnf.scenes.fit import psnr

    cuda = args.device.startswith("cuda")
    n, s = args.render_views, args.render_size
    c2w, k = render_cameras(scene, n, s)
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    scene.render_rgbd(c2w, k, s, s, args.chunk)  # warm-up (and compilation, if asked for)
    _sync(args.device)
    stats = getattr(scene, "march_stats", None)
    if stats is not None:
        stats.update({key: 0 for key in stats})
    t0 = time.perf_counter()
    reps = 0
    while True:
        out = scene.render_rgbd(c2w, k, s, s, args.chunk)
        reps += 1
        _sync(args.device)
        if time.perf_counter() - t0 > 3.0 or reps >= 20:
            break
    fps = reps * n / (time.perf_counter() - t0)
    figures: dict = {"render_frames_per_s": round(fps, 1), "render_size_px": s, "render_batch_views": n}
    figures["peak_gpu_memory_render_gib"] = torch.cuda.max_memory_allocated() / 2**30 if cuda else None
    if stats is not None and stats["rays"]:
        figures["render_rays_reaching_object_box"] = round(stats["marched_rays"] / stats["rays"], 3)
        figures["render_network_samples_per_ray"] = round(stats["samples"] / stats["rays"], 2)
        figures["render_march_rounds_per_batch"] = round(stats["rounds"] / reps, 1)
    # The same two frames by the dense quadrature over every sample the occupancy grid keeps (the
    # differentiable pass of training), against the fast renderer's output.
    if hasattr(scene, "march_stats"):
        o, d, z = camera_rays(c2w[:2], k, s, s)
        o, d = o.reshape(-1, 3).to(args.device), d.reshape(-1, 3).to(args.device)
        with torch.enable_grad():
            parts = [scene.render_rays(o[i : i + 8192], d[i : i + 8192]) for i in range(0, o.shape[0], 8192)]
        dense_rgb = torch.cat([p["rgb"].detach() for p in parts]).reshape(2, s, s, 3).clamp(0, 1).cpu()
        dense_depth = torch.cat([p["depth"].detach() for p in parts]).reshape(2, s, s).cpu() * z
        fast_rgb, fast_depth = out["rgb"][:2].cpu(), out["depth"][:2].cpu()
        figures["render_psnr_vs_dense_db"] = round(float(psnr(fast_rgb, dense_rgb).min()), 2)
        figures["render_max_depth_diff_vs_dense_m"] = float((fast_depth - dense_depth).abs().max())
    return figures


def render_only(args: argparse.Namespace) -> None:
    """``--load``: print the rendering figures of a fitted scene."""
    import resource

    import torch

    if args.device.startswith("cuda"):
        torch.backends.cuda.matmul.allow_tf32 = True
    scene = load_scene_for_rendering(args.load, args)
    figures = {
        "scene": args.load,
        "device": torch.cuda.get_device_name() if args.device.startswith("cuda") else "cpu",
        "half": args.half,
        "compile": args.compile,
        "march_kernel": args.march_kernel,
        **measure_rendering(scene, args),
        "peak_cpu_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
    }
    for key, value in figures.items():
        print(f"{key:>36}: {value}")
    if args.profile:
        profile_rendering(scene, args)


def profile_rendering(scene, args: argparse.Namespace) -> None:
    """Print the operators (CUDA kernels on a GPU) that took the most time in one batch of renders."""
    from torch.profiler import ProfilerActivity, profile

    s = args.render_size
    c2w, k = render_cameras(scene, args.render_views, s)
    cuda = args.device.startswith("cuda")
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=activities) as prof:
        scene.render_rgbd(c2w, k, s, s, args.chunk)
        _sync(args.device)
    key = "self_cuda_time_total" if cuda else "self_cpu_time_total"
    print(prof.key_averages().table(sort_by=key, row_limit=30, max_name_column_width=60))


def _sync(device: str) -> None:
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize()


if __name__ == "__main__":
    main()
