"""``tnf finetune``: continue a trained generator on a small dataset of another sensor.

``tnf finetune finetune.checkpoint=tn_cgan_digit/best.ckpt data.datasets=[omnitact_pairs] data.per_object=5``
loads the generator's weights (its config comes from the checkpoint; the optimisers start afresh), optionally
freezes some of its parameters (``finetune.freeze``), and trains on the new data, whose pairs carry the new
sensor's background image as a condition. Without ``finetune.checkpoint`` the same command trains
``cfg.generator`` from scratch on that data: the baseline of the transfer experiment. Writes
``<data_root>/models/<run_name>/`` like ``tnf train``; the source checkpoint is never modified.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

from tnf.artifacts import ArtifactStore
from tnf.errors import TnfError
from tnf.runtime import seed_everything
from tnf.stages.train import datamodule_from_cfg, dataset_names, fit_section, run_config


def resolve_checkpoint(value: str, data_root: Any) -> Path:
    """A checkpoint given as a path, as ``<run>/<file>`` under ``models/``, or as a run name (best.ckpt)."""

    p = Path(value).expanduser()
    if p.is_file():
        return p
    models = ArtifactStore(data_root).path("models")
    for cand in (models / value, models / value / "best.ckpt"):
        if cand.is_file():
            return cand
    raise TnfError(
        f"finetune.checkpoint: no checkpoint at {p} nor {models / value}[/best.ckpt]; train one with `tnf train`"
    )


def run(cfg: Any) -> dict[str, Any]:
    from omegaconf import OmegaConf
    from rich.console import Console

    from tnf.generators.names import finetune_run_name
    from tnf.generators.system import GeneratorSystem

    console = Console(highlight=False)
    f = cfg.finetune
    store = ArtifactStore(cfg.data_root)
    datasets = dataset_names(cfg)
    hp: dict[str, Any] = {
        "epochs": int(f.epochs),
        "decay_epochs": int(f.decay_epochs),
        "grid_rows": int(f.grid_rows),
        "finite_check_every": int(f.finite_check_every),
        "ema_decay": f.ema_decay,
    }
    overrides = {"lr": float(f.lr)} if f.lr is not None else {}
    source: dict[str, Any] = {}
    if f.checkpoint:
        ckpt = resolve_checkpoint(str(f.checkpoint), cfg.data_root)
        system = GeneratorSystem.from_checkpoint(ckpt, "cpu", generator_overrides=overrides, **hp)
        source = {"checkpoint": str(ckpt.resolve()), "checkpoint_hash": _file_hash(ckpt)}
        default_name = finetune_run_name(ckpt.parent.name, "", datasets)
    else:
        generator = cast(dict[str, Any], OmegaConf.to_container(cfg.generator, resolve=True))
        system = GeneratorSystem({**generator, **overrides}, **hp)
        default_name = finetune_run_name(None, system.hparams["generator"]["name"], datasets)
    spec = dict(system.hparams["generator"])
    frozen = system.generator.freeze([str(x) for x in f.freeze]) if f.freeze else []
    run_name = str(f.run_name or default_name)
    run_dir = store.path("models", run_name)
    config = run_config(cfg, "finetune", ("checkpoint",), generator=spec, source=source)
    if not f.force and store.is_done("models", run_name, config=config):
        console.print(f"[green]{run_name}[/]: fine-tuned with the same settings, skipped (finetune.force=true)")
        return {"run_dir": str(run_dir), "skipped": True}

    seed_everything(int(cfg.seed))
    dm = datamodule_from_cfg(cfg, datasets)
    if source and getattr(system.generator, "field", None) is not None:
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
    summary = fit_section(cfg, f, system, dm, run_dir, config, info)
    last = summary.get("last", {})
    console.print(
        f"[bold]{run_name}[/]: {summary['epochs']} epochs on {summary.get('train_pairs') or '?'} pairs; "
        f"val SSIM {last.get('val_ssim', float('nan')):.4f}, "
        f"val MSE {last.get('val_mse', float('nan')):.1f}"
    )
    return {"run_dir": str(run_dir), **summary}


def _file_hash(path: Path) -> str:
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]
