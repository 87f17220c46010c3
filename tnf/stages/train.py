"""``tnf train``: train a generator (``generator=tn_cgan|lee|cyclegan``) on paired datasets.

Reads the datasets of ``data.datasets`` (default: the one ``tnf pair`` builds), trains with the Lightning
trainer of ``trainer=`` (cpu, gpu, ddp) and logs with ``logger=`` (csv, tensorboard, wandb). Writes
``<data_root>/models/<run id>/`` (``tnf.generators.names``; ``train.run_name`` replaces the id): ``last.ckpt``,
``best.ckpt`` (lowest validation L1), ``grids/``, ``metrics.csv`` and ``manifest.json``. An unfinished run
resumes from ``last.ckpt``; a finished run with the same settings is skipped, unless its ``best.ckpt`` is gone:
then it is trained again.
"""

from __future__ import annotations

from typing import Any, NamedTuple, cast

from tnf.artifacts import ArtifactStore, identity
from tnf.data.settings import DataSettings
from tnf.errors import TnfError
from tnf.generators.settings import FinetuneSettings, TrainSettings
from tnf.registry import config_to_dict, from_dict
from tnf.runtime import resolve_precision, seed_everything, stage_console


class TrainPlan(NamedTuple):
    """What ``tnf train`` trains with a config, before any training."""

    checked: Any
    """``(registered name, Config)`` of the generator, checked once."""
    spec: dict[str, Any]
    """The generator's name and settings as plain data."""
    datasets: list[str]
    """Names of the paired datasets it trains on."""
    config: dict[str, Any]
    """The settings that define the model (``run_config``): their hash decides whether a finished run is
    skipped and ends the run id."""
    run_name: str
    """The run folder's name under ``models/``: ``train.run_name``, or the run id (``tnf.generators.names``)."""
    settings: TrainSettings
    """The ``train`` section."""


def plan(cfg: Any) -> TrainPlan:
    """What ``tnf train`` trains with ``cfg`` and where it goes (checks the generator's settings)."""
    from omegaconf import OmegaConf

    from tnf.generators.names import generator_option, run_id
    from tnf.generators.system import generator_config

    # Checked once: the system builds the generator from this Config, the run's hash records its fields.
    checked = generator_config(cast(dict[str, Any], OmegaConf.to_container(cfg.generator, resolve=True)))
    spec = {"name": checked[0], **config_to_dict(checked[1])}
    datasets = dataset_names(cfg)
    settings = from_dict(TrainSettings, cfg.train, where="train")
    config = run_config(cfg, "train", settings, datasets, generator=spec)
    name = settings.run_name or run_id(generator_option(spec["name"]), datasets[0], cfg.seed, config)
    return TrainPlan(checked, spec, datasets, config, name, settings)


def model_run(cfg: Any) -> str:
    """The run folder name under ``models/`` of the model ``tnf train`` trains with ``cfg``."""
    return plan(cfg).run_name


def run(cfg: Any) -> dict[str, Any]:
    """Train the generator of ``cfg``; returns ``run_name``, ``run_dir`` and the run's summary (``skipped``:
    true when a finished run with the same settings was there)."""
    from tnf.generators.names import new_run_note
    from tnf.generators.system import GeneratorSystem
    from tnf.generators.training import process_rank

    # Under a cluster launcher (torchrun, srun) every DDP process runs this stage; process 0 reports.
    console = stage_console(quiet=process_rank() != 0)
    checked, spec, datasets, config, run_name, t = plan(cfg)
    store = ArtifactStore(cfg.data_root)
    run_dir = store.path("models", run_name)
    state = "new" if t.force else run_state(store, run_name, config, console, "training")
    if state == "done":
        console.print(f"[green]{run_name}[/]: trained with the same settings, skipped (train.force=true to redo)")
        return {"run_name": run_name, "run_dir": str(run_dir), "skipped": True}
    if not t.run_name and (note := new_run_note(run_dir.parent, run_name, config)):
        console.print(note, markup=False)

    seed_everything(int(cfg.seed))
    dm = datamodule_from_cfg(cfg, datasets)
    system = GeneratorSystem(
        checked,
        epochs=t.epochs,
        decay_epochs=t.decay_epochs,
        grid_rows=t.grid_rows,
        finite_check_every=t.finite_check_every,
        ema_decay=t.ema_decay,
        compile_nets=t.compile,
    )
    console.print(f"training [bold]{spec['name']}[/] on {', '.join(datasets)} -> {run_dir}")
    info = {"generator": spec["name"], "datasets": datasets, "object_names": dm.object_names}
    summary = fit_section(cfg, t, system, dm, run_dir, config, info, fresh=state == "lost")
    _print_summary(console, run_name, summary)
    return {"run_name": run_name, "run_dir": str(run_dir), **summary}


def run_state(store: ArtifactStore, run_name: str, config: dict[str, Any], console: Any, doing: str) -> str:
    """Where model run ``run_name`` of settings ``config`` stands: ``done`` (finished with them, its best.ckpt in
    place), ``lost`` (finished, but the best.ckpt generate and evaluate load is gone: said on ``console``, then
    ``doing`` again from the start, since the finished run's last.ckpt leaves no epoch to resume) or ``new``."""
    if not store.is_done("models", run_name, config=config):
        return "new"
    if (store.path("models", run_name) / "best.ckpt").is_file():
        return "done"
    console.print(f"{run_name}: finished, but its best.ckpt is missing; {doing} it again", markup=False)
    return "lost"


def run_config(
    cfg: Any, section: str, settings: TrainSettings | FinetuneSettings, datasets: list[str], **extra: Any
) -> dict[str, Any]:
    """What identifies a model run of the ``train`` or ``finetune`` section (its hash decides whether a finished
    run is skipped and ends the run id, ``tnf.generators.names.run_id``): ``extra`` (the generator spec, a
    fine-tuning source), the data settings, the content of each of ``datasets`` (``dataset_hashes``), the run's
    ``settings`` (that section's, by ``tnf.artifacts.identity``), precision and seed."""
    return {
        **extra,
        "data": identity(data_settings(cfg)),
        "datasets": dataset_hashes(cfg, datasets),
        section: identity(settings),
        "precision": resolve_precision(str(cfg.trainer.precision), str(cfg.trainer.get("accelerator", "auto"))),
        "seed": int(cfg.seed),
    }


def fit_section(
    cfg: Any,
    section: TrainSettings | FinetuneSettings,
    system: Any,
    dm: Any,
    run_dir: Any,
    config: dict[str, Any],
    info: dict[str, Any],
    *,
    fresh: bool = False,
) -> dict[str, Any]:
    """Train ``system`` on ``dm`` into ``run_dir`` with the run settings of ``section`` (the ``train`` or
    ``finetune`` section's settings) and the ``trainer``, ``logger`` and ``callbacks`` groups; returns the run's
    summary. ``fresh``: start the run again even where ``section`` would resume it."""
    from omegaconf import OmegaConf

    from tnf.generators.callbacks import build_callbacks
    from tnf.generators.training import fit

    return fit(
        system,
        dm,
        run_dir,
        config=config,
        trainer_cfg=trainer_args(cfg),
        logger_cfg=cast(dict[str, Any], OmegaConf.to_container(cfg.logger, resolve=True)),
        callbacks=build_callbacks(cast(dict[str, Any], OmegaConf.to_container(cfg.callbacks, resolve=True))),
        resume=section.resume and not section.force and not fresh,
        progress=bool(cfg.progress),
        limit_train_batches=section.limit_train_batches,
        limit_val_batches=section.limit_val_batches,
        log_every_n_steps=section.log_every_n_steps,
        checkpoint_every_s=section.checkpoint_every_s,
        val_every_n_epochs=section.val_every_n_epochs if isinstance(section, FinetuneSettings) else 1,
        patience=section.patience if isinstance(section, TrainSettings) else None,
        min_delta=section.min_delta if isinstance(section, TrainSettings) else 0.0,
        info=info,
    )


def datamodule_from_cfg(cfg: Any, datasets: Any = None) -> Any:
    """``tnf.data.PairDataModule`` from the ``data`` section (``datasets`` overrides ``data.datasets``; an
    unset dataset name becomes the one ``tnf pair`` gives this config)."""
    from tnf.data import datamodule_from_config

    names = dataset_names(cfg) if datasets is None else [str(x) for x in datasets]
    return datamodule_from_config(data_settings(cfg), int(cfg.seed), cfg.data_root, names)


def data_settings(cfg: Any) -> DataSettings:
    """The ``data`` section of ``cfg`` as its settings (checked)."""
    return from_dict(DataSettings, cfg.data, where="data")


def dataset_names(cfg: Any) -> list[str]:
    """``data.datasets``, with an unset name (``pair.name: null``) replaced by the name ``tnf pair`` gives the
    dataset of this config."""
    from tnf.data.store import dataset_name

    listed = data_settings(cfg).datasets
    if listed is None:  # the dataset `tnf pair` builds with this config
        listed = [None]
    default = dataset_name(cfg.pair, str(cfg.sensor.name), str(cfg.scene.name))
    names = [str(x) if x not in (None, "None", "null", "") else default for x in listed]
    if not names:
        raise TnfError("data.datasets is empty: name the paired dataset(s) under pairs/ to train on")
    return names


def dataset_hashes(cfg: Any, datasets: list[str]) -> dict[str, str | None]:
    """Each dataset name under ``pairs/`` -> the key hash its manifest records (None while it is not built): a
    dataset rebuilt from other touches makes a new model run, not a skipped one."""
    store = ArtifactStore(cfg.data_root)
    return {name: (store.manifest("pairs", name) or {}).get("config_hash") for name in datasets}


def trainer_args(cfg: Any) -> dict[str, Any]:
    """Lightning Trainer arguments from the ``trainer`` group (accelerator, devices, precision, ...)."""
    from omegaconf import OmegaConf

    data = OmegaConf.to_container(cfg.trainer, resolve=True)
    assert isinstance(data, dict)
    return {str(k): v for k, v in data.items()}


def _print_summary(console: Any, run_name: str, summary: dict[str, Any]) -> None:
    last = summary.get("last", {})
    best = summary.get("best_val_l1")
    console.print(
        f"[bold]{run_name}[/]: {summary['epochs']} epochs on {summary.get('train_pairs') or '?'} pairs; "
        f"val SSIM {last.get('val_ssim', float('nan')):.4f}, "
        f"val MSE {last.get('val_mse', float('nan')):.1f}, val L1 {last.get('val_l1', float('nan')):.4f} "
        f"(best {best if best is not None else float('nan'):.4f}, in best.ckpt)"
    )
