"""Running a ``GeneratorSystem`` with Lightning: trainer, loggers, checkpoints, resume, run folder.

Shared by ``tnf train`` and ``tnf finetune``. A run folder ``<root>/models/<run_name>/`` holds ``last.ckpt``,
``best.ckpt`` (highest validation SSIM), ``grids/epoch_XXX.png``, ``metrics.csv`` (earlier parts of a
resumed run in ``metrics.partN.csv``), ``run.json`` (the run's
config, written when it starts, so a resumed run can be checked against it) and, once finished,
``manifest.json``.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any, cast

from tnf.artifacts import MANIFEST, config_hash, read_json, write_json
from tnf.errors import TnfError

RUN_FILE = "run.json"


def make_loggers(logger_cfg: Mapping[str, Any] | None, run_dir: Path) -> list[Any]:
    """CSV metrics (always, ``metrics.csv`` in the run folder) plus the configured logger.

    ``logger_cfg``: ``{name: csv | tensorboard | wandb, ...}``; wandb is imported only when selected and runs
    offline unless ``mode: online``.
    """
    from lightning.pytorch.loggers import CSVLogger

    loggers: list[Any] = [CSVLogger(save_dir=str(run_dir), name="", version="")]
    cfg = dict(logger_cfg or {})
    name = cfg.pop("name", "csv")
    if name in ("csv", None, "none"):
        return loggers
    if name == "tensorboard":
        try:
            import tensorboard  # noqa: F401
        except ImportError:
            raise TnfError("logger=tensorboard needs the tensorboard package: pip install 'tnf[tensorboard]'") from None
        from lightning.pytorch.loggers import TensorBoardLogger

        loggers.append(TensorBoardLogger(save_dir=str(run_dir), name="tensorboard", version="", **cfg))
    elif name == "wandb":
        from lightning.pytorch.loggers import WandbLogger

        mode = cfg.pop("mode", "offline")
        os.environ.setdefault("WANDB_MODE", mode)
        loggers.append(WandbLogger(save_dir=str(run_dir), name=run_dir.name, mode=mode, **cfg))
    else:
        raise TnfError(f"unknown logger {name!r}; available: csv, tensorboard, wandb")
    return loggers


def prepare_run_dir(run_dir: Path, config: Mapping[str, Any], resume: bool) -> Path | None:
    """Create the run folder; returns ``last.ckpt`` to resume from, or None to start afresh.

    A folder holding a run of another config is an error (rather than silently mixing two runs); with
    ``resume=False`` an unfinished earlier run is started again.
    """
    run_dir.mkdir(parents=True, exist_ok=True)
    last = run_dir / "last.ckpt"
    run_file = run_dir / RUN_FILE
    if run_file.is_file():
        old = read_json(run_file, "run file")
        if old.get("config_hash") != config_hash(config) and last.is_file():
            raise TnfError(
                f"{run_dir} holds a run with another config; choose another run name (train.run_name=...) "
                "or delete the folder"
            )
    write_json(run_file, {"config": config, "config_hash": config_hash(config)})
    if resume and last.is_file():
        # The CSV logger starts metrics.csv afresh; keep the earlier part of the run's history.
        old = run_dir / "metrics.csv"
        if old.is_file():
            k = 1
            while (run_dir / f"metrics.part{k}.csv").exists():
                k += 1
            old.rename(run_dir / f"metrics.part{k}.csv")
        return last
    for stale in ("last.ckpt", "best.ckpt", MANIFEST):
        (run_dir / stale).unlink(missing_ok=True)
    return None


def fit(
    system: Any,
    datamodule: Any,
    run_dir: str | os.PathLike[str],
    *,
    config: Mapping[str, Any],
    trainer_cfg: Mapping[str, Any],
    logger_cfg: Mapping[str, Any] | None = None,
    resume: bool = True,
    progress: bool = True,
    limit_train_batches: int | float | None = None,
    limit_val_batches: int | float | None = None,
    log_every_n_steps: int = 50,
    info: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Train ``system`` (a ``GeneratorSystem``) on ``datamodule`` into ``run_dir``; returns the summary that
    also goes into the run's ``manifest.json`` (best and last validation metrics, epochs, checkpoints).

    ``config`` is what the run is identified by (the manifest's config and hash); ``trainer_cfg`` holds
    Lightning Trainer arguments (accelerator, devices, precision, strategy, ...).
    """
    import lightning as L
    from lightning.pytorch.callbacks import ModelCheckpoint, RichProgressBar

    from tnf.generators.system import NonFiniteLoss

    run_dir = Path(run_dir)
    ckpt_path = prepare_run_dir(run_dir, config, resume)
    system.grid_dir = str(run_dir / "grids")
    checkpoint = ModelCheckpoint(
        dirpath=str(run_dir),
        filename="best",
        # L1, the loss the generators are trained on: SSIM favours an early, nearly uniform output on
        # smooth tactile images, and picked such checkpoints as "best".
        monitor="val_l1",
        mode="min",
        save_top_k=1,
        enable_version_counter=False,
        auto_insert_metric_name=False,
    )
    # last.ckpt after every epoch (Lightning's save_last writes it only when best.ckpt improves, so a resumed
    # run would lose the epochs since the best one).
    latest = ModelCheckpoint(
        dirpath=str(run_dir),
        filename="last",
        monitor=None,
        save_top_k=1,
        every_n_epochs=1,
        enable_version_counter=False,
    )
    callbacks: list[Any] = [checkpoint, latest]
    if progress:
        callbacks.append(RichProgressBar(leave=True))
    targs = dict(trainer_cfg)
    targs.setdefault("num_sanity_val_steps", 0)
    if targs.get("strategy") == "ddp":
        # A GAN step back-propagates through one network at a time, so each backward leaves parameters unused.
        targs["strategy"] = "ddp_find_unused_parameters_true"
    if str(targs.get("accelerator", "auto")) != "cpu":
        import torch

        targs.setdefault("benchmark", True)  # fixed 128 px shapes: let cuDNN pick the fastest kernels
        torch.set_float32_matmul_precision("high")  # TF32 for fp32 runs
    trainer = L.Trainer(
        default_root_dir=str(run_dir),
        max_epochs=system.hparams["epochs"],
        logger=make_loggers(logger_cfg, run_dir),
        callbacks=callbacks,
        enable_progress_bar=progress,
        enable_model_summary=progress,
        limit_train_batches=limit_train_batches,
        limit_val_batches=limit_val_batches,
        log_every_n_steps=log_every_n_steps,
        **targs,
    )
    with warnings.catch_warnings():
        # Small datasets and CPU runs trigger advice that does not apply to GAN training.
        warnings.filterwarnings("ignore", ".*does not have many workers.*")
        warnings.filterwarnings("ignore", ".*smaller than the logging interval.*")
        try:
            trainer.fit(system, datamodule=datamodule, ckpt_path=str(ckpt_path) if ckpt_path else None)
        except NonFiniteLoss as e:
            raise NonFiniteLoss(f"{e}; {_last_good(run_dir)}") from None
        except OSError as e:  # a full disk or a lost file system, most often while writing a checkpoint
            where = f" ({e.filename})" if e.filename else ""
            raise TnfError(
                f"training stopped by an I/O error: {e.strerror or e}{where}; {_last_good(run_dir)}; free space "
                "or fix the path, then rerun the same command to resume"
            ) from e
        except RuntimeError as e:
            if "DataLoader worker" not in str(e):
                raise
            raise TnfError(
                f"a data loader worker died ({str(e).splitlines()[0]}); {_last_good(run_dir)}; rerun the same "
                "command to resume (data.num_workers=0 loads in the main process, which shows the cause)"
            ) from e
    if trainer.interrupted:
        raise TnfError(f"training interrupted; resume with the same command (last checkpoint in {run_dir})")
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("val_")}
    best = checkpoint.best_model_score
    summary = {
        **dict(info or {}),
        "epochs": trainer.current_epoch,
        "global_step": trainer.global_step,
        "best_val_l1": float(best) if best is not None else None,
        "last": metrics,
        "checkpoints": {"last": "last.ckpt", "best": "best.ckpt"},
    }
    if trainer.is_global_zero:
        from tnf import __version__

        manifest = {
            **summary,
            "stage": "models",
            "item": [run_dir.name],
            "config": config,
            "config_hash": config_hash(config),
            "tnf_version": __version__,
        }
        write_json(run_dir / MANIFEST, manifest)
    return summary


def _last_good(run_dir: Path) -> str:
    """Where training can resume from, for error messages."""
    last = run_dir / "last.ckpt"
    return f"the last good checkpoint is {last}" if last.is_file() else "no checkpoint was saved yet"


def datamodule_from_cfg(cfg: Any, datasets: Any = None) -> Any:
    """``tnf.data.PairDataModule`` from the ``data`` section (``datasets`` overrides ``data.datasets``)."""
    from tnf.data import PairDataModule

    d = cfg.data
    names = dataset_names(cfg) if datasets is None else [str(x) for x in datasets]
    return PairDataModule(
        names,
        batch_size=int(d.batch_size),
        num_workers=int(d.num_workers),
        per_object=d.per_object,
        augment=bool(d.augment),
        pin_memory=bool(d.pin_memory),
        seed=int(cfg.seed),
        train_splits=list(d.train_splits),
        val_splits=list(d.val_splits),
        drop_last=bool(d.get("drop_last", False)),
        data_root=cfg.data_root,
    )


def dataset_names(cfg: Any) -> list[str]:
    """``data.datasets``, with an unset name (``pair.name: null``) replaced by the name ``tnf pair`` gives the
    dataset of this config."""
    from tnf.data.store import dataset_name

    listed = cfg.data.datasets
    if listed is None:  # the dataset `tnf pair` builds with this config
        listed = [None]
    names = [str(x) if x not in (None, "None", "null", "") else dataset_name(cfg) for x in listed]
    if not names:
        raise TnfError("data.datasets is empty: name the paired dataset(s) under pairs/ to train on")
    return names


def trainer_args(cfg: Any) -> dict[str, Any]:
    """Lightning Trainer arguments from the ``trainer`` group (accelerator, devices, precision, ...)."""
    from omegaconf import OmegaConf

    args = OmegaConf.to_container(cfg.trainer, resolve=True)
    assert isinstance(args, dict)
    return {str(k): v for k, v in args.items()}


def dataset_label(name: Any) -> str:
    """A short label of a dataset name or path, for run names."""
    return Path(str(name)).name


def run_section(section: Any, keys: tuple[str, ...] = ("resume", "force")) -> dict[str, Any]:
    """A stage section as plain data without the keys that do not change the result."""
    from omegaconf import OmegaConf

    data = cast(dict[str, Any], OmegaConf.to_container(section, resolve=True))
    assert isinstance(data, dict)
    return {k: v for k, v in data.items() if k not in keys}
