"""``tnf train``: train a generator (``generator=tn_cgan|lee|cyclegan``) on paired datasets.

Reads the datasets of ``data.datasets`` (default: the one ``tnf pair`` builds), trains with the Lightning
trainer of ``trainer=`` (cpu, gpu, ddp) and logs with ``logger=`` (csv, tensorboard, wandb). Writes
``<data_root>/models/<run_name>/``: ``last.ckpt``, ``best.ckpt`` (lowest validation L1), ``grids/``,
``metrics.csv`` and ``manifest.json``. An unfinished run resumes from ``last.ckpt``; a finished run with the
same settings is skipped.
"""

from __future__ import annotations

from typing import Any, cast


def run(cfg: Any) -> dict[str, Any]:
    from omegaconf import OmegaConf
    from rich.console import Console

    from tnf.artifacts import ArtifactStore
    from tnf.generators.system import GeneratorSystem, generator_spec
    from tnf.generators.training import (
        datamodule_from_cfg,
        dataset_label,
        dataset_names,
        fit,
        process_rank,
        run_section,
        trainer_args,
    )
    from tnf.runtime import seed_everything

    # Under a cluster launcher (torchrun, srun) every DDP process runs this stage; process 0 reports.
    console = Console(highlight=False, quiet=process_rank() != 0)
    t = cfg.train
    spec = generator_spec(cast(dict[str, Any], OmegaConf.to_container(cfg.generator, resolve=True)))
    datasets = dataset_names(cfg)
    run_name = str(t.run_name or f"{spec['name']}_{dataset_label(datasets[0] if datasets else 'data')}")
    store = ArtifactStore(cfg.data_root)
    run_dir = store.path("models", run_name)
    config = {
        "generator": spec,
        "data": run_section(cfg.data, ()),
        "train": run_section(t, ("resume", "force", "run_name", "checkpoint_every_s", "compile")),
        "precision": str(cfg.trainer.precision),
        "seed": int(cfg.seed),
    }
    if not t.force and store.is_done("models", run_name, config=config):
        console.print(f"[green]{run_name}[/]: trained with the same settings, skipped (train.force=true to redo)")
        return {"run_dir": str(run_dir), "skipped": True}

    seed_everything(int(cfg.seed))
    dm = datamodule_from_cfg(cfg, datasets)
    system = GeneratorSystem(
        spec,
        epochs=int(t.epochs),
        decay_epochs=int(t.decay_epochs),
        grid_rows=int(t.grid_rows),
        finite_check_every=int(t.finite_check_every),
        ema_decay=t.ema_decay,
        compile_nets=bool(t.compile),
    )
    console.print(f"training [bold]{spec['name']}[/] on {', '.join(datasets)} -> {run_dir}")
    summary = fit(
        system,
        dm,
        run_dir,
        config=config,
        trainer_cfg=trainer_args(cfg),
        logger_cfg=cast(dict[str, Any], OmegaConf.to_container(cfg.logger, resolve=True)),
        resume=bool(t.resume) and not bool(t.force),
        progress=bool(cfg.progress),
        limit_train_batches=t.limit_train_batches,
        limit_val_batches=t.limit_val_batches,
        log_every_n_steps=int(t.log_every_n_steps),
        checkpoint_every_s=float(t.checkpoint_every_s),
        info={"generator": spec["name"], "datasets": datasets, "object_names": dm.object_names},
    )
    _print_summary(console, run_name, summary)
    return {"run_dir": str(run_dir), **summary}


def _print_summary(console: Any, run_name: str, summary: dict[str, Any]) -> None:
    last = summary.get("last", {})
    best = summary.get("best_val_l1")
    console.print(
        f"[bold]{run_name}[/]: {summary['epochs']} epochs on {summary.get('train_pairs') or '?'} pairs; "
        f"val SSIM {last.get('val_ssim', float('nan')):.4f}, "
        f"val MSE {last.get('val_mse', float('nan')):.1f}, val L1 {last.get('val_l1', float('nan')):.4f} "
        f"(best {best if best is not None else float('nan'):.4f}, in best.ckpt)"
    )
