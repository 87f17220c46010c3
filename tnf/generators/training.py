"""Running a ``GeneratorSystem`` with Lightning: trainer, loggers, checkpoints, resume, run folder.

Shared by ``tnf train`` and ``tnf finetune``. A run folder ``<root>/models/<run_name>/`` holds ``last.ckpt``,
``best.ckpt`` (lowest validation L1), ``grids/epoch_XXX.png``, ``metrics.csv`` (the run's whole history, one row
per logging event, a resumed run's included), ``run.json`` (the run's config, written when it starts, so a
resumed run can be checked against it) and, once finished, ``manifest.json``.

A run killed at any moment (``kill -9``) and started again resumes from ``last.ckpt``, and its ``metrics.csv``
goes on from there: ``last.ckpt`` is in place only once the rows of its epochs are all in ``metrics.csv``
(``tnf.generators.callbacks.LatestCheckpoint``), the rows the killed run logged after it are dropped on
resuming (``keep_epochs``), and the CSV logger appends to the rows kept (``RunCSVLogger``).
"""

from __future__ import annotations

import contextlib
import csv
import io
import logging
import os
import signal
import threading
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import lightning
from lightning.pytorch.callbacks import Callback, ModelCheckpoint
from lightning.pytorch.loggers import CSVLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter
from lightning.pytorch.loggers.logger import rank_zero_experiment

from tnf.artifacts import MANIFEST, config_hash, exclusive, manifest_record, read_json, write_bytes, write_json
from tnf.errors import NonFiniteLoss, TnfError
from tnf.generators.callbacks import PENDING, LatestCheckpoint
from tnf.generators.names import RUN_FILE
from tnf.runtime import ignore_lightning_deprecations, lightning_logs_once, resolve_precision

#: The run's metrics, one CSV row per logging event (Lightning's ``CSVLogger`` layout).
METRICS = "metrics.csv"


class RunCSVLogger(CSVLogger):
    """Lightning's ``CSVLogger`` that continues the run folder's ``metrics.csv`` rather than deleting it: a
    resumed run appends its rows to those of its earlier part (``prepare_run_dir`` keeps the rows up to the
    checkpoint it resumes from)."""

    @property
    @rank_zero_experiment
    def experiment(self) -> Any:
        if self._experiment is None:
            self._fs.makedirs(self.root_dir, exist_ok=True)
            self._experiment = _ContinuingWriter(log_dir=self.log_dir)
        return self._experiment


class _ContinuingWriter(ExperimentWriter):
    """Lightning's CSV writer, starting from the columns of an existing ``metrics.csv`` and appending to it."""

    def __init__(self, log_dir: str) -> None:
        super().__init__(log_dir=log_dir)
        if os.path.isfile(self.metrics_file_path):
            with open(self.metrics_file_path, newline="") as f:
                self.metrics_keys = list(next(csv.reader(f), []))

    def _check_log_dir_exists(self) -> None:
        pass  # Lightning's deletes metrics.csv here


def make_loggers(logger_cfg: Mapping[str, Any] | None, run_dir: Path) -> list[Any]:
    """CSV metrics (always, ``metrics.csv`` in the run folder) plus the configured logger.

    ``logger_cfg``: ``{name: csv | tensorboard | wandb, ...}``; wandb is imported only when selected and runs
    offline unless ``mode: online``.
    """
    loggers: list[Any] = [RunCSVLogger(save_dir=str(run_dir), name="", version="")]
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
    ``resume=False`` an unfinished earlier run is started again. Resuming keeps the rows of ``metrics.csv`` up to
    the checkpoint's epoch; starting afresh deletes it. Only process 0 of a distributed run writes.
    """
    last = run_dir / "last.ckpt"
    run_file = run_dir / RUN_FILE
    if run_file.is_file():
        old = read_json(run_file, "run file")
        if old.get("config_hash") != config_hash(config) and last.is_file():
            raise TnfError(
                f"{run_dir} holds a run with another config; choose another run name (train.run_name=...) "
                "or delete the folder"
            )
    if process_rank() != 0:
        # Another process of a distributed run that a cluster launcher started (torchrun, srun): process 0
        # prepares the folder; this one only needs to know where to resume from.
        return last if resume and last.is_file() else None
    run_dir.mkdir(parents=True, exist_ok=True)
    write_json(run_file, {"config": config, "config_hash": config_hash(config)})
    # A checkpoint that a killed run wrote but never put in place (LatestCheckpoint): its epoch's rows may be
    # missing from metrics.csv, so the run resumes from the one before.
    (run_dir / f"last.ckpt{PENDING}").unlink(missing_ok=True)
    if resume and last.is_file():
        keep_epochs(run_dir / METRICS, _progress(last, monitor="val_l1")[0])
        return last
    for stale in ("last.ckpt", "best.ckpt", MANIFEST, METRICS):
        (run_dir / stale).unlink(missing_ok=True)
    return None


def keep_epochs(metrics: Path, epochs: int) -> None:
    """Keep the rows of the first ``epochs`` epochs in ``metrics`` (a ``metrics.csv``; rows without an epoch
    too) and drop the later ones, which a resumed run logs again. A missing file is left missing."""
    if not metrics.is_file():
        return
    with open(metrics, newline="") as f:
        reader = csv.DictReader(f)
        columns = list(reader.fieldnames or [])
        rows = list(reader)
    kept = [r for r in rows if not r.get("epoch") or int(float(r["epoch"])) < epochs]
    if len(kept) == len(rows):
        return
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=columns)
    writer.writeheader()
    writer.writerows(kept)
    write_bytes(metrics, text.getvalue().encode())


def fit(
    system: Any,
    datamodule: Any,
    run_dir: str | os.PathLike[str],
    *,
    config: Mapping[str, Any],
    trainer_cfg: Mapping[str, Any],
    logger_cfg: Mapping[str, Any] | None = None,
    callbacks: Sequence[Callback] | None = None,
    resume: bool = True,
    progress: bool = True,
    limit_train_batches: int | float | None = None,
    limit_val_batches: int | float | None = None,
    log_every_n_steps: int = 50,
    checkpoint_every_s: float = 0.0,
    val_every_n_epochs: int = 1,
    patience: int | None = None,
    min_delta: float = 0.0,
    info: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Train ``system`` (a ``GeneratorSystem``) on ``datamodule`` into ``run_dir``; returns the summary that
    also goes into the run's ``manifest.json`` (best and last validation metrics, epochs, checkpoints).

    ``config`` is what the run is identified by (the manifest's config and hash); ``trainer_cfg`` holds
    Lightning Trainer arguments (accelerator, devices, precision, strategy, ...; precision ``auto``:
    ``tnf.runtime.resolve_precision``); ``callbacks`` the run's
    configurable callbacks (``tnf.generators.callbacks.build_callbacks``, default: those of the ``callbacks``
    group's default option), which join the checkpoints and the progress bar. ``last.ckpt`` is written at
    the end of an epoch once ``checkpoint_every_s`` seconds have passed since it was last written (0: after
    every epoch), and always after the last epoch. Validation (with ``best.ckpt`` and the image grids) runs after
    every ``val_every_n_epochs``-th epoch. ``patience``: stop once that many validations in a row have not raised
    the validation SSIM above its best by more than ``min_delta`` (the summary's ``plateau`` says whether it
    did); None trains every epoch.
    """
    if checkpoint_every_s < 0:
        raise TnfError(f"checkpoint_every_s must be >= 0 seconds (0: after every epoch), got {checkpoint_every_s}")
    import lightning as L
    from lightning.pytorch.callbacks import RichProgressBar

    from tnf.generators.callbacks import WeightAverage, build_callbacks

    extra = list(build_callbacks() if callbacks is None else callbacks)
    if getattr(system, "generator_ema", None) is not None and not any(isinstance(c, WeightAverage) for c in extra):
        raise TnfError(
            "ema_decay keeps a weight average, but the weight_average callback that updates it is left out "
            "(callbacks.weight_average=null)"
        )
    run_dir = Path(run_dir)
    with contextlib.ExitStack() as held:
        if process_rank() == 0:  # (the other processes of a distributed run train it with process 0)
            busy = f"another process is training {run_dir.name} (in {run_dir}); wait for it, or name this run"
            held.enter_context(exclusive(run_dir, f"{busy} another way (train.run_name, finetune.run_name)"))
        ckpt_path = prepare_run_dir(run_dir, config, resume)
        targs = dict(trainer_cfg)
        if "precision" in targs:  # auto: bf16-mixed where the device runs it natively
            targs["precision"] = resolve_precision(str(targs["precision"]), str(targs.get("accelerator", "auto")))
        targs.setdefault("num_sanity_val_steps", 0)
        targs["strategy"] = ddp_strategy(targs.get("strategy", "auto"), fixed_graph=system.generator.fixed_graph())
        on_gpu = str(targs.get("accelerator", "auto")) != "cpu"
        if on_gpu:
            targs.setdefault("benchmark", True)  # fixed 128 px shapes: let cuDNN pick the fastest kernels
        every: list[Any] = [*checkpoints(run_dir, checkpoint_every_s), ProcessSetup(tf32=on_gpu), *extra]
        if patience is not None:
            from lightning.pytorch.callbacks import EarlyStopping

            # Counted in validations; its state is in last.ckpt, so a resumed run counts on.
            every.append(EarlyStopping(monitor="val_ssim", mode="max", patience=patience, min_delta=min_delta))
        if progress:
            every.append(RichProgressBar(leave=True))
        _quiet_trainer_start()
        trainer = L.Trainer(
            default_root_dir=str(run_dir),
            max_epochs=system.hparams["epochs"],
            logger=make_loggers(logger_cfg, run_dir),
            callbacks=every,
            enable_progress_bar=progress,
            enable_model_summary=progress,
            limit_train_batches=limit_train_batches,
            limit_val_batches=limit_val_batches,
            log_every_n_steps=log_every_n_steps,
            check_val_every_n_epoch=val_every_n_epochs,
            **targs,
        )
        _run(trainer, system, datamodule, ckpt_path, run_dir)
        if trainer.interrupted:
            raise TnfError(f"training interrupted; resume with the same command (last checkpoint in {run_dir})")
        summary = _summary(trainer, datamodule, run_dir, info)
        if patience is not None:
            summary["plateau"] = {
                "patience": patience,
                "min_delta": min_delta,
                "stopped": summary["epochs"] < int(system.hparams["epochs"]),
            }
        if trainer.is_global_zero:
            write_json(run_dir / MANIFEST, manifest_record("models", [run_dir.name], config, summary))
        return summary


def _summary(trainer: Any, datamodule: Any, run_dir: Path, info: Mapping[str, Any] | None) -> dict[str, Any]:
    """A finished run's summary: ``info``, its pairs, epochs, steps, best and last validation metrics."""
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("val_")}
    # Read from last.ckpt rather than the trainer: with spawned DDP processes this process's trainer never
    # trained, and only the callback metrics come back from them.
    epochs, global_step, best = _progress(run_dir / "last.ckpt", monitor="val_l1")
    return {
        **dict(info or {}),
        "train_pairs": _train_pairs(datamodule),
        "epochs": epochs,
        "global_step": global_step,
        "best_val_l1": best,
        "last": metrics,
        "world_size": trainer.world_size,
        "precision": str(trainer.precision),
        "checkpoints": {"last": "last.ckpt", "best": "best.ckpt"},
    }


def checkpoints(run_dir: Path, every_s: float) -> list[ModelCheckpoint]:
    """The run's checkpoint callbacks: ``best.ckpt`` (the weights of the epoch of lowest validation L1) and
    ``last.ckpt`` (``LatestCheckpoint``: everything a resumed run needs, at most every ``every_s`` seconds)."""
    best = ModelCheckpoint(
        dirpath=str(run_dir),
        filename="best",
        # L1, the loss the generators are trained on: SSIM favours an early, nearly uniform output on
        # smooth tactile images, and picked such checkpoints as "best".
        monitor="val_l1",
        mode="min",
        save_top_k=1,
        # The weights only (a third of the size): best.ckpt is for generating and fine-tuning; resuming
        # uses last.ckpt.
        save_weights_only=True,
        enable_version_counter=False,
        auto_insert_metric_name=False,
    )
    # last.ckpt at the end of an epoch, at most every every_s seconds (Lightning's save_last writes it only
    # when best.ckpt improves, so a resumed run would lose the epochs since the best one). A checkpoint with
    # the optimiser's state is about 12 bytes per parameter (1 GB for tn_cgan at its paper size): written
    # after each of many short epochs, the writes took longer than the training.
    latest = LatestCheckpoint(
        dirpath=str(run_dir),
        filename="last",
        monitor=None,
        save_top_k=1,
        every_n_epochs=1,
        save_on_train_epoch_end=True,  # after the epoch's validation, if any; with none, still after the epoch
        enable_version_counter=False,
        every_s=every_s,
    )
    return [best, latest]


def _run(trainer: Any, system: Any, datamodule: Any, ckpt_path: Path | None, run_dir: Path) -> None:
    """``trainer.fit``, from ``ckpt_path`` where given; its failures as one-line tnf errors that say where
    training can resume from."""
    from torch.multiprocessing import ProcessRaisedException

    sigint = signal.getsignal(signal.SIGINT)
    with warnings.catch_warnings():
        quiet_advice()
        try:
            trainer.fit(system, datamodule=datamodule, ckpt_path=str(ckpt_path) if ckpt_path else None)
        except SystemExit as e:
            # Lightning ends a fit on Ctrl+C (KeyboardInterrupt) with exit(1), after its shutdown (callbacks'
            # on_exception, loggers finalised), and ignores SIGINT from then on. As tnf's own interruption (the
            # one line and exit 130 of the tnf command), with the SIGINT handler put back; last.ckpt is where it
            # was, so the same command resumes. SIGTERM (a scheduler's stop) ends it with status 0, as success:
            # a tnf error instead. Any other exit passes on as it is.
            from lightning.pytorch.utilities.exceptions import SIGTERMException

            if isinstance(e, SIGTERMException):
                raise TnfError(
                    f"training stopped by SIGTERM; {_last_good(run_dir)}: the same command resumes"
                ) from None
            if not isinstance(e.__context__, KeyboardInterrupt):
                raise
            if sigint is not None and threading.current_thread() is threading.main_thread():
                signal.signal(signal.SIGINT, sigint)
            raise e.__context__ from None
        except NonFiniteLoss as e:
            raise NonFiniteLoss(f"{e}; {_last_good(run_dir)}") from None
        except ProcessRaisedException as e:
            # A spawned DDP process failed; its exception arrives as a traceback text. A tnf error (bad data,
            # a diverged loss) is shown as the one line it is.
            raise _worker_error(e, run_dir) from None
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


def quiet_advice() -> None:
    """Silence Lightning advice that does not apply to GAN training here: small datasets and CPU runs (few
    loader workers, short epochs), DDP's per-epoch training losses, which are process 0's (averaging them
    over processes would synchronise every step), and a run folder that is not empty, which tnf made itself
    (``prepare_run_dir``: the run file first, and on resuming the metrics it keeps); and Lightning's own
    deprecations (``tnf.runtime.ignore_lightning_deprecations``)."""
    warnings.filterwarnings("ignore", ".*does not have many workers.*")
    warnings.filterwarnings("ignore", ".*smaller than the logging interval.*")
    warnings.filterwarnings("ignore", ".*when logging on epoch level in distributed setting.*")
    warnings.filterwarnings("ignore", ".*(Experiment logs|Checkpoint) directory .* exists and is not empty.*")
    ignore_lightning_deprecations()


class _NoAdvice(logging.Filter):
    """Drops two of Lightning's start-up notices: the advertisement for its cloud logger, printed at every
    Trainer's start, and the advice to set the fp32 matmul precision on GPUs with tensor cores, which tnf sets
    itself (``ProcessSetup(tf32=True)``) after Lightning has checked; and its notice of a Ctrl+C, which the
    ``tnf`` command reports itself (``_run``)."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        return not any(
            s in message for s in ("litlogger", "set_float32_matmul_precision", "Detected KeyboardInterrupt")
        )


_NO_ADVICE = _NoAdvice()


def _quiet_trainer_start() -> None:
    """Install ``_NoAdvice`` on the logger Lightning prints its start-up notices with (once per process), and
    print each notice once (``tnf.runtime.lightning_logs_once``)."""
    logger = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    if _NO_ADVICE not in logger.filters:
        logger.addFilter(_NO_ADVICE)
    lightning_logs_once()


class ProcessSetup(Callback):
    """Settings of the process that trains, applied there: spawned DDP processes start with the default
    warning filters and matmul precision, not the caller's.

    Args:
        tf32: fp32 matrix products in TF32 (``torch.set_float32_matmul_precision("high")``) on GPUs.
    """

    def __init__(self, tf32: bool = False):
        self.tf32 = tf32

    def setup(self, trainer: Any, pl_module: Any, stage: str) -> None:
        quiet_advice()
        if self.tf32:
            import torch

            torch.set_float32_matmul_precision("high")


def ddp_strategy(strategy: Any, fixed_graph: bool = False) -> Any:
    """The Lightning strategy for a ``trainer.strategy`` value: ``ddp`` and ``ddp_spawn`` become a
    ``DDPStrategy`` that starts its processes with ``torch.multiprocessing`` (spawn); anything else is passed on
    as it is. With ``fixed_graph`` (``Generator.fixed_graph``: one backward through the same parameters every
    step) DDP uses a static graph; otherwise it finds the parameters each step leaves without gradients.

    Lightning's ``ddp`` would start the other processes by running the command line again, which the ``tnf``
    command cannot be (its stage name is not part of the Python command line, and under ``-m`` the sweep would
    run again in every process). When a cluster launcher starts the processes itself (torchrun, srun with one
    task per device), Lightning detects it and starts none: every process then runs the whole stage.
    """
    if strategy not in ("ddp", "ddp_spawn"):
        return strategy
    from lightning.pytorch.strategies import DDPStrategy

    # A GAN step back-propagates through one network at a time, so each backward leaves parameters unused.
    static = fixed_graph and static_graph_synced()
    graph: dict[str, Any] = {"static_graph": True} if static else {"find_unused_parameters": True}
    # "popen" starts no process where a cluster launcher has started them (spawn would start more).
    if processes_started_externally():
        return DDPStrategy(**graph, start_method="popen")
    import multiprocessing

    if multiprocessing.get_start_method(allow_none=True) not in (None, "spawn", "fork", "forkserver"):
        # In a job of hydra/launcher=joblib (a loky worker) the default start method is "loky", which the
        # spawned processes would be told to use and cannot find.
        multiprocessing.set_start_method("spawn", force=True)
    return DDPStrategy(**graph, start_method="spawn")


def static_graph_synced() -> bool:
    """True where Lightning averages the gradients of manual optimisation's first step under a static graph.
    Lightning before 2.6 does not (its issue 18086): ``tests/generators/test_ddp.py`` sees the first step
    differ from one process's on the whole batch with Lightning 2.4."""
    major, minor = (int(x) for x in lightning.__version__.split(".")[:2])
    return (major, minor) >= (2, 6)


def processes_started_externally() -> bool:
    """True inside a job whose processes a cluster launcher started, one per device (torchrun, srun, LSF,
    MPI), as Lightning's Trainer detects it."""
    from lightning.fabric.plugins.environments import (
        LSFEnvironment,
        MPIEnvironment,
        SLURMEnvironment,
        TorchElasticEnvironment,
    )

    return any(env.detect() for env in (TorchElasticEnvironment, SLURMEnvironment, LSFEnvironment, MPIEnvironment))


def process_rank() -> int:
    """This process's global rank as a cluster launcher sets it (RANK, LOCAL_RANK, SLURM_PROCID); 0 outside
    one, and in the process that spawns DDP processes itself."""
    from lightning.fabric.utilities.rank_zero import rank_zero_only

    return int(getattr(rank_zero_only, "rank", 0) or 0)


def _train_pairs(datamodule: Any) -> int | None:
    """How many pairs the training split served (after ``data.per_object`` and ``data.extra_touches``)."""
    if not hasattr(datamodule, "dataset") or not hasattr(datamodule, "train_splits"):
        return None
    return len(datamodule.dataset(datamodule.train_splits))


def _progress(last: Path, monitor: str) -> tuple[int, int, float | None]:
    """Epochs done, optimiser steps and the best ``monitor`` value recorded in checkpoint ``last``."""
    import torch

    if not last.is_file():
        return 0, 0, None
    ckpt = torch.load(last, map_location="cpu", weights_only=True, mmap=True)
    best = None
    for state in ckpt.get("callbacks", {}).values():
        if isinstance(state, dict) and state.get("monitor") == monitor and state.get("best_model_score") is not None:
            best = float(state["best_model_score"])
    # "epoch" is the index of the epoch the checkpoint was written at the end of.
    return int(ckpt.get("epoch", -1)) + 1, int(ckpt.get("global_step", 0)), best


def _worker_error(e: Exception, run_dir: Path) -> Exception:
    """A TnfError from the last line of a spawned process's traceback when it is a tnf error, else ``e``."""
    import re

    lines = [ln for ln in str(e).strip().splitlines() if ln.strip()]
    m = re.match(r"^(tnf\.[\w.]+): (.+)$", lines[-1]) if lines else None
    if m is None:
        return e
    return TnfError(f"{m.group(2)} (in DDP process {getattr(e, 'error_index', '?')}); {_last_good(run_dir)}")


def _last_good(run_dir: Path) -> str:
    """Where training can resume from, for error messages."""
    last = run_dir / "last.ckpt"
    return f"the last good checkpoint is {last}" if last.is_file() else "no checkpoint was saved yet"
