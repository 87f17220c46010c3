"""Run-wide helpers every stage uses: the compute device, seeding, progress bars and warning filters."""

from __future__ import annotations

import contextlib
import logging
import random
import threading
import warnings
from collections.abc import Iterator
from typing import Any

import tnf
from tnf.errors import TnfError


@contextlib.contextmanager
def interrupts_held() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT) while the body runs; one pressed meanwhile arrives as a KeyboardInterrupt when it
    ends. For imports that catch ``BaseException`` around their optional parts (trimesh's): a Ctrl-C inside them
    is otherwise swallowed, and leaves a module half imported. The press is noted by a handler of its own, which
    Python runs in the main thread whichever thread the signal reaches. Outside the main thread, or under a
    handler other than Python's default, it holds nothing."""
    import signal

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.getsignal(signal.SIGINT)
    if old is not signal.default_int_handler:
        yield
        return
    pressed: list[int] = []
    signal.signal(signal.SIGINT, lambda signum, frame: pressed.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)
    if pressed:
        raise KeyboardInterrupt


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


def job_device(device: str, shard: tuple[int, int] | None) -> str:
    """The device of one job of a sweep over object shards (``tnf.objects.shard``): ``cuda`` becomes
    ``cuda:<shard mod GPUs>`` when this process sees several GPUs, so that the jobs of a sweep on one machine
    spread over its GPUs; a job that sees one GPU (a SLURM job given one) and every other device keep
    ``device``. ``device``: a resolved torch device string (``resolve_device``); ``shard``: the job's
    ``(shard, shards)`` (``tnf.objects.shard_of``), None outside such a sweep."""
    if shard is None or device != "cuda":
        return device
    import torch

    count = torch.cuda.device_count()
    if count <= 1:
        return device
    index = shard[0] % count
    torch.cuda.set_device(index)
    return f"cuda:{index}"


def environment(device: str) -> dict[str, Any]:
    """Where a result was made: the accelerator (the GPU's name, or the CPU's), CPU cores, Python and the
    versions of tnf (with its git commit where tnf runs from a checkout) and of the libraries the numbers depend
    on. Stored in each evaluated run's results and shown in the report."""
    import os
    import platform
    import sys
    from importlib import metadata

    import torch

    def version(package: str) -> str | None:
        try:
            return metadata.version(package)
        except metadata.PackageNotFoundError:
            return None

    if device.startswith("cuda") and torch.cuda.is_available():
        accelerator = torch.cuda.get_device_name(torch.device(device))
    else:
        accelerator = _cpu_name() or "CPU"
    return {
        "accelerator": accelerator,
        "device": device,
        "cpu_cores": os.cpu_count(),
        "python": platform.python_version(),
        "platform": sys.platform,
        "tnf": tnf.__version__,
        "commit": _git_commit(),
        "torch": torch.__version__,
        "warp": version("warp-lang"),
        "lightning": version("lightning"),
    }


#: ``/proc/cpuinfo`` flags of CPUs that run bf16 matrix products natively (x86 AVX-512 BF16 or AMX; Arm's bf16).
BF16_CPU_FLAGS = frozenset({"avx512_bf16", "amx_bf16", "bf16"})


def resolve_precision(precision: str, accelerator: str = "auto") -> str:
    """Lightning's ``precision`` for a trainer: ``auto`` -> ``bf16-mixed`` where the device runs bf16 natively
    (a CUDA GPU that supports it; a CPU with a flag of ``BF16_CPU_FLAGS``), else ``32-true``. Autocast works
    everywhere, but on a CPU without those instructions bf16 trains slower than float32. Any other value passes
    through. ``accelerator``: the trainer's (``cpu``, ``gpu``, ``cuda`` or ``auto``: a GPU where one is visible).
    """
    import torch

    if precision != "auto":
        return precision
    if accelerator != "cpu" and torch.cuda.is_available():
        return "bf16-mixed" if torch.cuda.is_bf16_supported() else "32-true"
    return "bf16-mixed" if cpu_flags() & BF16_CPU_FLAGS else "32-true"


def cpu_flags() -> frozenset[str]:
    """The CPU's feature flags from ``/proc/cpuinfo`` (x86 ``flags``, Arm ``Features``); empty elsewhere."""
    return frozenset((_cpuinfo("flags", "Features") or "").split())


def _cpu_name() -> str | None:
    import platform

    return _cpuinfo("model name") or platform.processor() or None


def _cpuinfo(*keys: str) -> str | None:
    """The value of the first line of ``/proc/cpuinfo`` whose key is one of ``keys``; None without the file."""
    from pathlib import Path

    cpuinfo = Path("/proc/cpuinfo")
    if not cpuinfo.is_file():
        return None
    for line in cpuinfo.read_text(errors="replace").splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip() in keys:
            return value.strip()
    return None


def _git_commit() -> str | None:
    """The short commit of the checkout tnf runs from, with ``+changes`` if tracked files differ from it; None
    where tnf is installed from a package (or git is missing)."""
    import subprocess
    from pathlib import Path

    here = Path(__file__).resolve().parent
    if not (here.parent / ".git").exists():
        return None
    try:
        git = ["git", "-C", str(here.parent)]
        commit = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=10)
        if commit.returncode != 0:
            return None
        dirty = subprocess.run([*git, "diff", "--quiet", "HEAD", "--"], capture_output=True, timeout=10).returncode
    except (OSError, subprocess.SubprocessError):
        return None
    return commit.stdout.strip() + ("+changes" if dirty == 1 else "")


def seed_everything(seed: int) -> None:
    """Seed Python, NumPy and torch (all devices)."""
    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def step_seed(seed: int, step: int) -> int:
    """A 64-bit seed for training step ``step`` of a fit seeded with ``seed`` (mixed, so that nearby seeds
    and steps give unrelated streams; the CPU generator keeps only the low 32 bits)."""
    import numpy as np

    return int(np.random.SeedSequence((seed % 2**64, step)).generate_state(1, np.uint64)[0])


def stage_console(**kwargs: Any) -> Any:
    """The rich console a stage prints to (``kwargs`` as ``rich.console.Console``'s). Lines and table titles are
    not wrapped at the console's width, so that a printed path stays whole on one line (80 columns when the
    output is not a terminal)."""
    from rich.console import Console

    return Console(highlight=False, soft_wrap=True, **kwargs)


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


# What Warp's native library prints on a machine without an NVIDIA driver, where tnf runs on the CPU by design.
_NO_CUDA_DRIVER = "Could not find or load the NVIDIA CUDA driver"
_warp_lock = threading.Lock()
_warp_started = False


def init_warp() -> None:
    """Initialise Warp without its start-up banner, its notice for every kernel module it loads, or its warning
    that a CPU-only machine has no CUDA driver (logged at DEBUG instead); its other warnings and errors still
    print. Only Warp's default level (INFO) is raised: a level set before (``warp.config.log_level =
    warp.LOG_DEBUG`` to see what Warp does) is kept. Cheap after the first call, which alone starts Warp (under
    a lock: kernels call this on every launch, from any thread)."""
    global _warp_started
    import warp as wp

    if wp.config.log_level == wp.LOG_INFO:
        wp.config.log_level = wp.LOG_WARNING
    if _warp_started:
        return
    with _warp_lock:
        if _warp_started:
            return
        with _without_native_line(_NO_CUDA_DRIVER) as dropped:
            wp.init()
        _warp_started = True
    if dropped:
        logging.getLogger(__name__).debug("no NVIDIA CUDA driver: Warp runs on the CPU only")


@contextlib.contextmanager
def _without_native_line(text: str) -> Iterator[list[str]]:
    """Hold back what native code writes to the process's stderr (file descriptor 2) inside the block, then write
    it out without the lines that contain ``text``; the list yielded receives the lines dropped. Where the
    descriptor cannot be redirected, everything prints as it is."""
    import os
    import sys
    import tempfile

    dropped: list[str] = []
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):
        yield dropped
        return
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        try:
            yield dropped
        finally:
            with contextlib.suppress(OSError, ValueError):
                sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            held.seek(0)
            lines = held.read().decode(errors="replace").splitlines(keepends=True)
            dropped.extend(line for line in lines if text in line)
            kept = "".join(line for line in lines if text not in line)
            if kept:
                sys.stderr.write(kept)
                sys.stderr.flush()


def available_memory() -> int | None:
    """Bytes of memory this machine can still give a process (Linux ``MemAvailable``), or None where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def check_memory(need: float, what: str, settings: str, share: float = 0.8) -> None:
    """Refuse (one-line TnfError) work estimated to need ``need`` bytes when that is over ``share`` of the memory
    available: ``what`` says which work, ``settings`` which settings drive the figure and their values."""
    have = available_memory()
    if have is not None and need > share * have:
        raise TnfError(
            f"{what} would need about {need / 2**30:.1f} GiB of memory ({settings}); this machine has "
            f"{have / 2**30:.1f} GiB available: lower them"
        )
