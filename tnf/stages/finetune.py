"""``tnf finetune``: continue a trained generator on a small dataset of another sensor.

``tnf finetune finetune.checkpoint=tn_cgan-digit-hashgrid-seed0 data.datasets=[omnitact_pairs] data.per_object=5``
loads the generator's weights (its config comes from the checkpoint; the optimisers start afresh), optionally
freezes some of its parameters (``finetune.freeze``), and trains on the new data, whose pairs carry the new
sensor's background image as a condition. Without ``finetune.checkpoint`` the same command trains
``cfg.generator`` from scratch on that data: the baseline of the transfer experiment. Writes
``<data_root>/models/<run id>/`` like ``tnf train`` (``<generator option>+<transfer option>-...``,
``tnf.generators.names``; ``finetune.run_name`` replaces the id); the source checkpoint is never modified.

With ``finetune.presses`` (``transfer=real``, ``real_fs``, ``real_plus``) the data are real indenter presses
instead: a press folder or ``taxim:SENSOR``, as ``tnf calibrate`` takes it. The stage writes the press pairs of
``finetune.press_train`` (and ``press_val``) to ``<data_root>/pairs/presses-<folder>-<sensor>/``
(``tnf.real.finetune.write_press_pairs``), trains on them, and scores the held-out presses ``press_test``
against their real frames (``realism.md``, ``realism.json`` and ``realism.png`` in the run folder).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

from tnf.artifacts import ArtifactStore
from tnf.errors import TnfError
from tnf.generators.settings import FinetuneSettings
from tnf.registry import from_dict
from tnf.runtime import seed_everything, stage_console
from tnf.stages.train import data_settings, datamodule_from_cfg, dataset_names, fit_section, run_config, run_state


def resolve_checkpoint(value: str, data_root: Any) -> Path:
    """A checkpoint given as a path, as ``<run>/<file>`` under ``models/``, or as a run (best.ckpt). A run is
    a folder name or a run family (``tnf.generators.names.run_family``, a run id without its hash) with one
    finished run."""
    from tnf.generators.names import find_run

    p = Path(value).expanduser()
    if p.is_file():
        return p
    models = ArtifactStore(data_root).path("models")
    for cand in (models / value, models / value / "best.ckpt"):
        if cand.is_file():
            return cand
    run, _, file = value.partition("/")
    found = find_run(models, run)
    if found is not None and (models / found / (file or "best.ckpt")).is_file():
        return models / found / (file or "best.ckpt")
    raise TnfError(
        f"finetune.checkpoint: no checkpoint at {p} nor {models / value}[/best.ckpt], and no finished run "
        f"{run}-<hash>; train one with `tnf train`"
    )


def run(cfg: Any) -> dict[str, Any]:
    from omegaconf import OmegaConf

    from tnf.generators.names import finetune_option, new_run_note, run_id
    from tnf.generators.system import GeneratorSystem

    console = stage_console()
    f = from_dict(FinetuneSettings, cfg.finetune, where="finetune")
    store = ArtifactStore(cfg.data_root)
    datasets = dataset_names(cfg)
    real = _press_settings(cfg, f) if f.presses else None
    hp: dict[str, Any] = {
        "epochs": f.epochs,
        "decay_epochs": f.decay_epochs,
        "grid_rows": f.grid_rows,
        "finite_check_every": f.finite_check_every,
        "ema_decay": f.ema_decay,
    }
    overrides = {"lr": f.lr} if f.lr is not None else {}
    source: dict[str, Any] = {}
    ckpt: Path | None = None
    if f.checkpoint:
        ckpt = resolve_checkpoint(f.checkpoint, cfg.data_root)
        system = GeneratorSystem.from_checkpoint(ckpt, "cpu", generator_overrides=overrides, **hp)
        source = {"checkpoint": str(ckpt.resolve()), "checkpoint_hash": _file_hash(ckpt)}
    else:
        generator = cast(dict[str, Any], OmegaConf.to_container(cfg.generator, resolve=True))
        system = GeneratorSystem({**generator, **overrides}, **hp)
    extra: dict[str, Any] = {}
    if real is not None:
        datasets, extra["presses"] = _press_dataset(cfg, store, real, ckpt, datasets, console)
    spec = dict(system.hparams["generator"])
    frozen = system.generator.freeze(f.freeze) if f.freeze else []
    config = run_config(cfg, "finetune", f, datasets, generator=spec, source=source, **extra)
    run_name = f.run_name or run_id(finetune_option(spec["name"]), datasets[0], cfg.seed, config)
    run_dir = store.path("models", run_name)
    state = "new" if f.force else run_state(store, run_name, config, console, "fine-tuning")
    if state == "done":
        done = {"run_name": run_name, "run_dir": str(run_dir), "skipped": True}
        if real is not None and real["test"] and not (run_dir / "realism.json").is_file():
            # Trained, but its scoring never finished (stopped, or failed): score it now
            console.print(f"[green]{run_name}[/]: fine-tuned with the same settings; scoring its held-out presses")
            return {**done, "press_realism": _score_presses(cfg, real, run_dir, console)}
        console.print(
            f"[green]{run_name}[/]: fine-tuned with the same settings, skipped (finetune.force=true trains it again)"
        )
        return done
    if not f.run_name and (note := new_run_note(run_dir.parent, run_name, config)):
        console.print(note, markup=False)

    seed_everything(int(cfg.seed))
    dm = datamodule_from_cfg(cfg, datasets)
    if ckpt is not None and getattr(system.generator, "field", None) is not None:
        # A surface field (tnf.generators.field) knows objects by their ids in the source model's training data.
        trained = (store.manifest("models", ckpt.parent.name) or {}).get("object_names")
        if trained is not None and list(trained) != list(dm.object_names):
            raise TnfError(
                f"the surface field of {ckpt} knows objects by their order in its training data, {list(trained)}; "
                f"the fine-tuning data's objects are {list(dm.object_names)}: fine-tune on datasets of the same "
                "objects in the same order (object_names), or from scratch"
            )
    what = f"from {source['checkpoint']}" if source else "from scratch"
    console.print(
        f"fine-tuning [bold]{spec['name']}[/] {what} on {', '.join(datasets)} -> {run_dir}"
        + (f" ({len(frozen)} parameter tensors frozen)" if frozen else "")
    )
    info = {
        "generator": spec["name"],
        "datasets": datasets,
        "source": source,
        "frozen": frozen,
        "object_names": dm.object_names,
    }
    summary = fit_section(cfg, f, system, dm, run_dir, config, info, fresh=state == "lost")
    last = summary.get("last", {})
    console.print(
        f"[bold]{run_name}[/]: {summary['epochs']} epochs on {summary.get('train_pairs') or '?'} pairs; "
        f"val SSIM {last.get('val_ssim', float('nan')):.4f}, "
        f"val MSE {last.get('val_mse', float('nan')):.1f}"
    )
    if real is not None and real["test"]:
        summary["press_realism"] = _score_presses(cfg, real, run_dir, console)
    return {"run_name": run_name, "run_dir": str(run_dir), **summary}


def _press_settings(cfg: Any, f: FinetuneSettings) -> dict[str, Any]:
    """The checked ``finetune.press*`` settings (``f``: the ``finetune`` section), the press folder and the
    sensor (one-line errors first)."""
    from tnf.real.finetune import check_split
    from tnf.real.generated import REFERENCES
    from tnf.real.presses import check_depths, check_indices, resolve_presses
    from tnf.registry import SENSORS, split_spec

    check_split(f.press_train, f.press_val, f.press_test, "finetune")
    if f.press_reference not in REFERENCES:
        raise TnfError(f"finetune.press_reference must be one of {', '.join(REFERENCES)}, got {f.press_reference!r}")
    if data_settings(cfg).per_object is not None:
        raise TnfError(
            "data.per_object subsamples the touches of each object; with finetune.presses every training press "
            "is used: set data.per_object=null (finetune.press_train chooses the presses)"
        )
    presses = resolve_presses(str(f.presses), cfg.data_root)
    for setting in ("press_train", "press_val", "press_test"):
        check_indices(presses, getattr(f, setting), f"finetune.{setting}")
    used = [*f.press_train, *f.press_val, *f.press_test]
    scaled = [presses.presses[i].depth_mm * f.press_depth_scale for i in used]
    check_depths(scaled, presses.radius_mm, f"finetune.press_depth_scale={f.press_depth_scale:g}", presses=used)
    name, spec = split_spec(cfg.sensor, "sensor")
    sensor = SENSORS.build({"name": name, **spec})
    return {
        "presses": presses,
        "sensor": sensor,
        "train": f.press_train,
        "val": f.press_val,
        "test": f.press_test,
        "depth_scale": f.press_depth_scale,
        "reference": f.press_reference,
        "sim_pairs": f.press_sim_pairs,
    }


def _press_dataset(
    cfg: Any, store: ArtifactStore, real: dict[str, Any], ckpt: Path | None, datasets: list[str], console: Any
) -> tuple[list[str], dict[str, Any]]:
    """Write (or find up to date) the press pairs under ``pairs/``; returns ``[their name]`` for the data
    module and what identifies them for the run's config. Framed as the source checkpoint's training data, or
    from scratch as the simulated dataset of this config where it exists."""
    import dataclasses

    from tnf.data.datamodule import resolve_dataset
    from tnf.real.finetune import presses_digest, write_press_pairs
    from tnf.real.generated import checkpoint_framing, dataset_framing

    presses, sensor = real["presses"], real["sensor"]
    sim = None
    if real["sim_pairs"] or ckpt is None:
        try:
            sim = resolve_dataset(datasets[0], cfg.data_root)
        except TnfError:
            if real["sim_pairs"]:
                raise
    framing = (checkpoint_framing(ckpt) if ckpt is not None else dataset_framing(sim)).with_sensor(sensor)
    real["framing"] = framing
    key = {
        "presses": str(presses.folder),
        "digest": presses_digest(presses),
        "sensor": sensor.describe(),
        "train": real["train"],
        "val": real["val"],
        "depth_scale": real["depth_scale"],
        "reference": real["reference"],
        "framing": dataclasses.asdict(framing),
        "sim": {"dataset": str(sim), "pairs": real["sim_pairs"], "seed": int(cfg.seed)} if real["sim_pairs"] else None,
    }
    name = f"presses-{presses.folder.name}-{sensor.name}"
    if store.is_done("pairs", name, config=key):
        console.print(f"press pairs {store.path('pairs', name)} are up to date")
    else:
        with store.writing("pairs", name, config=key) as tmp:
            info = write_press_pairs(
                presses, sensor, real["train"], tmp, val=real["val"], depth_scale=real["depth_scale"],
                framing=framing, reference=real["reference"], sim=sim, sim_pairs=real["sim_pairs"],
                seed=int(cfg.seed), device="cpu",
            )  # fmt: skip
        console.print(
            f"press pairs: {info['counts']['train']} training, {info['counts']['val']} validation pairs of "
            f"{presses.folder} -> {store.path('pairs', name)}"
        )
    return [name], {"name": name, "config_hash": (store.manifest("pairs", name) or {}).get("config_hash")}


def _score_presses(cfg: Any, real: dict[str, Any], run_dir: Path, console: Any) -> dict[str, Any]:
    """Generate the test presses with the run's last checkpoint, score them against the real frames (the run's
    ``realism.md``, ``.json``, ``.png``) and return the run's mean of each metric."""
    from tnf.real.finetune import write_press_realism
    from tnf.real.report import table

    record = write_press_realism(
        run_dir / "last.ckpt", real["presses"], real["sensor"], real["test"], run_dir,
        framing=real["framing"], depth_scale=real["depth_scale"], reference=real["reference"],
        seed=int(cfg.seed), label=run_dir.name,
    )  # fmt: skip
    console.print(table(record["mean"], record["seconds_per_frame"]))
    console.print(f"held-out presses {real['test']} scored: {run_dir / 'realism.md'}")
    return record["mean"][run_dir.name]


def _file_hash(path: Path) -> str:
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]
