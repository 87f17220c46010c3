"""Run-wide helpers every stage uses: the compute device, seeding, progress bars and warning filters."""

from __future__ import annotations

import contextlib
import logging
import random
import warnings
from collections.abc import Iterator
from typing import Any

from tnf.errors import TnfError


def resolve_device(name: str = "auto") -> str:
    """``auto`` -> ``cuda`` when a GPU is visible, else ``cpu``; ``cpu``/``cuda``/``cuda:N`` pass through."""
    import torch

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise TnfError(f"device={name!r} but no CUDA GPU is visible; use device=cpu or device=auto")
    if name != "cpu" and not name.startswith("cuda"):
        raise TnfError(f"device must be auto, cpu, cuda or cuda:N, got {name!r}")
    return name


def warp_device(torch_device: str) -> str:
    """The warp device name for a torch device string (``cuda`` -> ``cuda:0``)."""
    return "cuda:0" if torch_device == "cuda" else torch_device


def seed_everything(seed: int) -> None:
    """Seed Python, NumPy and torch (all devices)."""
    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


@contextlib.contextmanager
def progress(enabled: bool = True, transient: bool = False) -> Iterator[Any]:
    """A rich progress display: ``with progress() as p: t = p.add_task("capture", total=n); p.advance(t)``.

    When disabled (``progress=false`` in the config, or in tests) the same calls do nothing.
    """
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    p = Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        disable=not enabled,
        transient=transient,
    )
    with p:
        yield p


def ignore_lightning_deprecations() -> None:
    """Silence Lightning's use of torch's deprecated ``LeafSpec`` (a FutureWarning that is Lightning's to fix,
    not the user's), in the current warning filters."""
    warnings.filterwarnings("ignore", r".*isinstance\(treespec, LeafSpec\)", FutureWarning)


def lightning_logs_once() -> None:
    """Print Lightning's notices once. Importing ``lightning`` gives its package logger a console handler of its
    own, and the notices also propagate to the root logger; under the ``tnf`` command the root logger already
    writes to the console and the job's log file (Hydra's job logging), so every notice showed twice. Where the
    root logger has handlers, Lightning's own console handler is dropped; elsewhere Lightning prints as it does."""
    if not logging.getLogger().handlers:
        return
    lightning_logger = logging.getLogger("lightning")
    for handler in list(lightning_logger.handlers):
        if type(handler) is logging.StreamHandler:
            lightning_logger.removeHandler(handler)


def init_warp() -> None:
    """Initialise Warp (once per process; a no-op after) without its start-up banner and its notice for every
    kernel module it loads; its warnings and errors still print. Only Warp's default level (INFO) is raised: a
    level set before (``warp.config.log_level = warp.LOG_DEBUG`` to see what Warp does) is kept."""
    import warp as wp

    if wp.config.log_level == wp.LOG_INFO:
        wp.config.log_level = wp.LOG_WARNING
    wp.init()
