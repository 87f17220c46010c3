"""``tnf fit-scene``: fit a scene representation (cfg.scene: nerf, hashgrid) to each captured object.

Input per object: ``<data_root>/capture/<source>/<object>/`` (``tnf capture``). Output:
``<data_root>/scenes/<scene>/<source>/<object>/`` with ``scene.pt`` (``tnf.scenes.load_scene``),
``metrics.json`` (PSNR/SSIM on held-out views, depth error, training time) and ``preview.png``.

Objects: ``object=NAME``, else ``object_names``, else every captured object of the source, fitted one
after the other in this process. ``shard=I shards=N`` fits every N-th of them from number I: the sweep
``-m shards=N 'shard=range(N)'`` fits them as N jobs of the Hydra launcher (docs/cluster.md). Objects already
fitted with the same settings and capture are skipped; an interrupted fit resumes from its last checkpoint.
``fit.batch_objects=K`` (hash grids) fits the objects to do in groups of K, each group in one training loop
(``tnf.scenes.batched``); an interrupted group resumes from the group's checkpoint. ``fit.workers=N`` fits them
in N processes on this machine, worker i as the job ``shard=i shards=N`` would (``tnf.stages.local_workers``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from typing import Any

from tnf.artifacts import ArtifactStore
from tnf.errors import TnfError
from tnf.registry import SCENES, from_dict, split_spec
from tnf.runtime import job_device, progress, resolve_device, seed_everything, stage_console
from tnf.stages import data_seed, run_shard, shard_share

log = logging.getLogger(__name__)


def selected_objects(cfg: Any, store: Any, source: str) -> list[str]:
    """Object names to fit: cfg.object, else cfg.object_names, else every captured object of ``source``."""
    if cfg.object:
        return [str(cfg.object)]
    if cfg.object_names:
        return [str(n) for n in cfg.object_names]
    names = store.items("capture", source)
    if not names:
        raise TnfError(
            f"no captured objects of source {source!r} in {store.path('capture', source)}; run `tnf capture`"
        )
    return names


def _for_scene(settings: Any, kind: str) -> Any:
    """``settings`` (``FitSettings``) for scenes of ``kind``: the hash grid's speed-ups (``train_kernel``,
    ``batch_objects``, which experiments such as the quick start set) are off for other kinds, with a warning,
    so that ``scene=nerf`` fits one object at a time with the same key as without them."""
    if kind == "hashgrid" or not (settings.train_kernel or settings.batch_objects > 1):
        return settings
    log.warning(
        "fit.train_kernel=%s and fit.batch_objects=%d speed up hashgrid scenes only: %s scenes fit one at a time "
        "without them",
        str(settings.train_kernel).lower(),
        settings.batch_objects,
        kind,
    )
    return dataclasses.replace(settings, train_kernel=False, batch_objects=1)


def run(cfg: Any) -> list[dict[str, Any]]:
    """Fit every selected object (in ``fit.workers`` processes when above 1); returns one summary row per
    object."""
    plan = _plan(cfg)
    workers = _worker_shares(plan, cfg)
    if len(workers) > 1:
        from tnf.stages.local_workers import run_workers

        log.info("fit-scene: %d objects to fit in %d worker processes", len(plan.todo), len(workers))
        with progress(cfg.progress) as p:
            rows = plan.done + run_workers("fit-scene", cfg, workers, p)
    else:
        with progress(cfg.progress) as p:
            rows = plan.done + _fit(plan, cfg, p)
    rows.sort(key=lambda r: plan.names.index(r["object"]))
    _print_table(rows, f"fit-scene {plan.kind} -> {plan.store.path('scenes', plan.kind, plan.source)}")
    return rows


def worker_rows(cfg: Any, p: Any) -> list[dict[str, Any]]:
    """One worker's share (``cfg.shard``) of ``run``'s objects to fit, fitted in this process: their summary rows
    (``tnf.stages.local_workers``; the parent has the rows of those done before); ``p``: the progress display."""
    return _fit(_plan(cfg), cfg, p)


@dataclasses.dataclass
class _Plan:
    """What ``run`` fits: the objects of this job, the rows of those already done, and a job per object to fit."""

    settings: Any
    kind: str
    source: str
    store: ArtifactStore
    device: str
    names: list[str]
    captures: dict[str, Any]
    done: list[dict[str, Any]]
    todo: list[dict[str, Any]]  # per object: name, item, spec, config, size


def _plan(cfg: Any) -> _Plan:
    from tnf.scenes.settings import FitSettings

    settings = from_dict(FitSettings, cfg.fit, where="fit")
    kind, params = split_spec(cfg.scene, "scene")
    settings = _for_scene(settings, kind)
    SCENES.config(kind, params)  # fail early on a bad scene config
    source, _ = split_spec(cfg.objects, "objects")
    device = job_device(resolve_device(cfg.device), run_shard(cfg))
    store = ArtifactStore(cfg.data_root)
    store.clean_partials("scenes")
    names = shard_share(selected_objects(cfg, store, source), cfg)  # a job of a sweep over shards: its share
    # Check every input before the first (long) fit.
    captures = {}
    for name in names:
        captures[name] = store.require(
            "capture", source, name, hint=f"run `tnf capture object={name}` first (objects={source})"
        )
    done: list[dict[str, Any]] = []
    todo: list[dict[str, Any]] = []
    for name in names:
        capture_manifest = store.manifest("capture", source, name) or {}
        spec = {"name": kind, **params}
        if spec.get("bound") is None and capture_manifest.get("radius_m"):
            # The capture knows the object's bounding sphere: the tightest cube that holds it.
            spec["bound"] = 1.02 * float(capture_manifest["radius_m"])
        config = {
            "scene": spec,
            # The dataclass, so that fields out of the identity (``batch_objects`` of 1) stay out of the key.
            "fit": settings,
            "seed": data_seed(cfg),
            "capture": capture_manifest.get("config_hash"),
        }
        item = (kind, source, name)
        if store.is_done("scenes", *item, config=config):
            done.append({"object": name, "status": "skipped (done)"})
            continue
        todo.append(
            {"name": name, "item": item, "spec": spec, "config": config, "size": _object_size(capture_manifest)}
        )
    return _Plan(settings, kind, source, store, device, names, captures, done, todo)


def _worker_shares(plan: _Plan, cfg: Any) -> list[tuple[int, int, str, float]]:
    """The worker processes of ``fit.workers`` that have objects to fit: ``(shard, shards, label, planned
    steps)`` each; none outside a job's own share (a job of a sweep over shards fits its share itself)."""
    n = min(plan.settings.workers, len(plan.todo))
    if n <= 1 or run_shard(cfg) is not None:
        return []
    steps = plan.settings.resolved(plan.kind).steps
    todo = {job["name"] for job in plan.todo}
    out = []
    for i in range(n):
        mine = [name for name in plan.names[i::n] if name in todo]
        if mine:
            loops = -(-len(mine) // plan.settings.batch_objects)
            out.append((i, n, f"fit {plan.kind} {i + 1}/{n} ({_label(mine)})", float(steps * loops)))
    return out


def _label(names: list[str]) -> str:
    return ", ".join(names) if len(names) <= 3 else f"{names[0]} ... {names[-1]}"


def _fit(plan: _Plan, cfg: Any, p: Any) -> list[dict[str, Any]]:
    """Fit ``plan``'s objects to do in this process, one at a time or in groups of ``fit.batch_objects``; returns
    their summary rows."""
    from tnf.scenes.fit import fit_object

    settings, kind, source, store, device = plan.settings, plan.kind, plan.source, plan.store, plan.device
    rows: list[dict[str, Any]] = []
    steps = settings.resolved(kind).steps
    together = settings.batch_objects
    if together == 1:
        for job in plan.todo:
            name = job["name"]
            seed_everything(data_seed(cfg))
            task = p.add_task(f"fit {kind} {name}", total=steps)
            resume = store.path("scenes", ".resume", kind, source, f"{name}.pt")
            t0 = time.perf_counter()

            def on_step(step: int, loss: float, task: Any = task) -> None:
                p.update(task, completed=step + 1)

            with store.writing(
                "scenes", *job["item"], config=job["config"], info={"object": name, "source": source}
            ) as tmp:
                metrics = fit_object(
                    job["spec"],
                    plan.captures[name],
                    tmp,
                    settings,
                    device=device,
                    resume_path=resume,
                    on_step=on_step,
                    seed=data_seed(cfg),
                    size_m=job["size"],
                )
            rows.append(_fitted_row(name, metrics, time.perf_counter() - t0, kind))
    else:
        for i in range(0, len(plan.todo), together):
            group = plan.todo[i : i + together]
            rows += _fit_group(group, plan.captures, settings, kind, source, store, device, cfg, p)
    return rows


def _fit_group(
    group: list[dict[str, Any]],
    captures: dict[str, Any],
    settings: Any,
    kind: str,
    source: str,
    store: ArtifactStore,
    device: str,
    cfg: Any,
    p: Any,
) -> list[dict[str, Any]]:
    """Fit the objects of ``group`` together (``tnf.scenes.batched.fit_objects``), each into its own item; the
    group resumes from its own checkpoint. Returns their summary rows."""
    from tnf.scenes.batched import fit_objects, group_resume_name

    names = [job["name"] for job in group]
    seed_everything(data_seed(cfg))
    task = p.add_task(f"fit {kind} x{len(names)} ({_label(names)})", total=settings.resolved(kind).steps)
    resume = store.path("scenes", ".resume", kind, source, group_resume_name(names))
    t0 = time.perf_counter()

    def on_step(step: int, loss: float) -> None:
        p.update(task, completed=step + 1)

    with contextlib.ExitStack() as stack:
        tmps = [
            stack.enter_context(
                store.writing(
                    "scenes", *job["item"], config=job["config"], info={"object": job["name"], "source": source}
                )
            )
            for job in group
        ]
        results = fit_objects(
            [job["spec"] for job in group],
            [captures[n] for n in names],
            tmps,
            settings,
            device=device,
            resume_path=resume,
            on_step=on_step,
            seed=data_seed(cfg),
            sizes_m=[job["size"] for job in group],
            names=names,
        )
    seconds = (time.perf_counter() - t0) / len(names)
    return [_fitted_row(n, m, seconds, kind) for n, m in zip(names, results, strict=True)]


def _fitted_row(name: str, metrics: dict[str, Any], seconds: float, kind: str) -> dict[str, Any]:
    """The summary row of a fitted object (``seconds``: its wall time, or its share of its group's)."""
    metrics.pop("train_log", None)
    log.info("fitted %s %s: %s", kind, name, {k: metrics.get(k) for k in ("psnr", "ssim", "steps")})
    return {"object": name, "status": "fitted", "seconds": seconds, **metrics}


def _print_table(rows: list[dict[str, Any]], title: str) -> None:
    """One line per object: its status, image and depth errors on held-out views, and times."""
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
    stage_console().print(table)


def _object_size(manifest: dict[str, Any]) -> float | None:
    size = manifest.get("size_m")
    return float(max(size)) if isinstance(size, list) and size else None
