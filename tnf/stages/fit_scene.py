"""``tnf fit-scene``: fit a scene representation (cfg.scene: nerf, hashgrid) to each captured object.

Input per object: ``<data_root>/capture/<source>/<object>/`` (``tnf capture``). Output:
``<data_root>/scenes/<scene>/<source>/<object>/`` with ``scene.pt`` (``tnf.scenes.load_scene``),
``metrics.json`` (PSNR/SSIM on held-out views, depth error, training time) and ``preview.png``.

Objects: ``object=NAME``, else ``object_names``, else every captured object of the source, fitted one
after the other in this process. ``shard=I shards=N`` fits every N-th of them from number I: the sweep
``-m shards=N 'shard=range(N)'`` fits them as N jobs of the Hydra launcher (docs/cluster.md). Objects already
fitted with the same settings and capture are skipped; an interrupted fit resumes from its last checkpoint.
"""

from __future__ import annotations

import logging
import time
from typing import Any

from tnf.artifacts import ArtifactStore
from tnf.errors import TnfError
from tnf.registry import SCENES, config_to_dict, from_dict, split_spec
from tnf.runtime import job_device, progress, resolve_device, seed_everything
from tnf.stages import run_shard, shard_share

log = logging.getLogger(__name__)


def selected_objects(cfg: Any, store: Any, source: str) -> list[str]:
    """Object names to fit: cfg.object, else cfg.object_names, else every captured object of ``source``."""
    if cfg.object:
        return [str(cfg.object)]
    if cfg.object_names:
        return [str(n) for n in cfg.object_names]
    names = [item[1] for item in store.items("capture", 2) if item[0] == source]
    if not names:
        raise TnfError(
            f"no captured objects of source {source!r} in {store.path('capture', source)}; run `tnf capture`"
        )
    return names


def run(cfg: Any) -> list[dict[str, Any]]:
    """Fit every selected object; returns one summary row per object."""
    from tnf.scenes.fit import fit_object
    from tnf.scenes.settings import FitSettings

    settings = from_dict(FitSettings, cfg.fit, where="fit")
    kind, params = split_spec(cfg.scene, "scene")
    SCENES.config(kind, params)  # fail early on a bad scene config
    source, _ = split_spec(cfg.objects, "objects")
    part = run_shard(cfg)
    device = job_device(resolve_device(cfg.device), part)
    store = ArtifactStore(cfg.data_root)
    store.clean_partials("scenes")
    names = shard_share(selected_objects(cfg, store, source), cfg)  # a job of a sweep over shards: its share
    # Check every input before the first (long) fit.
    captures = {}
    for name in names:
        captures[name] = store.require(
            "capture", source, name, hint=f"run `tnf capture object={name}` first (objects={source})"
        )
    rows: list[dict[str, Any]] = []
    with progress(cfg.progress) as p:
        for name in names:
            item = (kind, source, name)
            capture_manifest = store.manifest("capture", source, name) or {}
            spec = {"name": kind, **params}
            if spec.get("bound") is None and capture_manifest.get("radius_m"):
                # The capture knows the object's bounding sphere: the tightest cube that holds it.
                spec["bound"] = 1.02 * float(capture_manifest["radius_m"])
            config = {
                "scene": spec,
                "fit": config_to_dict(settings),
                "seed": cfg.seed,
                "capture": capture_manifest.get("config_hash"),
            }
            if store.is_done("scenes", *item, config=config):
                rows.append({"object": name, "status": "skipped (done)"})
                continue
            seed_everything(cfg.seed)
            steps = settings.resolved(kind).steps
            task = p.add_task(f"fit {kind} {name}", total=steps)
            resume = store.path("scenes", ".resume", kind, source, f"{name}.pt")
            t0 = time.perf_counter()

            def on_step(step: int, loss: float, task: Any = task) -> None:
                p.update(task, completed=step + 1)

            with store.writing("scenes", *item, config=config, info={"object": name, "source": source}) as tmp:
                metrics = fit_object(
                    spec,
                    captures[name],
                    tmp,
                    settings,
                    device=device,
                    resume_path=resume,
                    on_step=on_step,
                    seed=cfg.seed,
                    size_m=_object_size(capture_manifest),
                )
            metrics.pop("train_log", None)
            rows.append({"object": name, "status": "fitted", "seconds": time.perf_counter() - t0, **metrics})
            log.info("fitted %s %s: %s", kind, name, {k: metrics.get(k) for k in ("psnr", "ssim", "steps")})
    _print_table(rows, f"fit-scene {kind} -> {store.path('scenes', kind, source)}")
    return rows


def _print_table(rows: list[dict[str, Any]], title: str) -> None:
    """One line per object: its status, image and depth errors on held-out views, and times."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title, header_style="bold")
    for col in ("object", "status", "PSNR dB", "SSIM", "depth err %", "train s", "total s"):
        table.add_column(col)
    for r in rows:
        rel = r.get("depth_error_median_rel")
        table.add_row(
            r["object"],
            r["status"],
            f"{r['psnr']:.2f}" if "psnr" in r else "",
            f"{r['ssim']:.3f}" if "ssim" in r else "",
            f"{100 * rel:.2f}" if rel is not None else "",
            f"{r['train_seconds']:.1f}" if "train_seconds" in r else "",
            f"{r['seconds']:.1f}" if "seconds" in r else "",
        )
    Console(highlight=False).print(table)


def _object_size(manifest: dict[str, Any]) -> float | None:
    size = manifest.get("size_m")
    return float(max(size)) if isinstance(size, list) and size else None
