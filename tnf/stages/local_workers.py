"""A stage's objects spread over worker processes on this machine.

Worker ``i`` of ``n`` is the job ``shard=i shards=n`` of a sweep over object shards (docs/cluster.md), started by
the stage itself: it makes the same items with the same settings. Warp runs a CPU kernel on one thread, so on a
CPU ``n`` processes of ``cores / n`` threads each keep the cores busy where one process leaves all but one idle
during each kernel (fit-scene's hash-grid encoding).

A worker reports its progress as a count of steps in a file the parent reads, and its summary rows as JSON.
"""

from __future__ import annotations

import importlib
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from tnf.artifacts import write_bytes, write_json
from tnf.errors import TnfError

log = logging.getLogger(__name__)

_THREADS_ENV = "TNF_WORKER_THREADS"
_TAIL_LINES = 3


def cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


class StepFile:
    """The progress display a worker's stage gets in place of rich's (``add_task``, ``update``): it writes the
    steps completed over all its tasks to ``path``, at most every ``every`` seconds and at each task's end."""

    def __init__(self, path: str | os.PathLike[str], every: float = 0.5):
        self.path = Path(path)
        self.every = every
        self._done: list[float] = []
        self._totals: list[float] = []
        self._written = 0.0

    def add_task(self, description: str, total: float | None = None, **_: Any) -> int:
        self._done.append(0.0)
        self._totals.append(float(total or 0))
        return len(self._done) - 1

    def update(self, task: int, completed: float | None = None, advance: float | None = None, **_: Any) -> None:
        if completed is not None:
            self._done[task] = float(completed)
        if advance is not None:
            self._done[task] += float(advance)
        now = time.monotonic()
        if now - self._written >= self.every or self._done[task] >= self._totals[task]:
            self._written = now
            write_bytes(self.path, str(sum(self._done)).encode())

    def advance(self, task: int, advance: float = 1) -> None:
        self.update(task, advance=advance)


def run_workers(
    stage: str,
    cfg: Any,
    workers: Sequence[tuple[int, int, str, float]],
    p: Any,
) -> list[dict[str, Any]]:
    """Run ``stage``'s worker function (the module's ``worker_rows(cfg, progress)``) in one process per entry of
    ``workers``: ``(shard, shards, label of its bar, planned steps)``, each with ``cfg`` but for ``shard`` and
    ``shards``, and ``cores() // len(workers)`` threads. ``p``: the parent's progress display (a bar per worker).
    Returns the workers' rows in the order of ``workers``. A worker that fails raises a TnfError naming it with the
    last lines it wrote; an interrupt stops every worker."""
    from omegaconf import OmegaConf

    threads = max(1, cores() // len(workers))
    with tempfile.TemporaryDirectory(prefix="tnf-workers-") as tmp:
        folder = Path(tmp)
        config = folder / "config.yaml"
        config.write_text(OmegaConf.to_yaml(cfg, resolve=True))
        env = dict(os.environ, OMP_NUM_THREADS=str(threads), **{_THREADS_ENV: str(threads)})
        procs, tasks, logs = [], [], []
        try:
            for shard, shards, label, planned in workers:
                out = folder / f"worker-{shard}"
                out.mkdir()
                logs.append(open(out / "log.txt", "w"))  # noqa: SIM115 (closed below)
                cmd = [sys.executable, "-m", __name__, stage, str(config), str(shard), str(shards), str(out)]
                procs.append(subprocess.Popen(cmd, env=env, stdout=logs[-1], stderr=subprocess.STDOUT))
                tasks.append(p.add_task(label, total=planned))
            _wait(procs, folder, workers, tasks, p)
        except BaseException:
            _stop(procs)
            raise
        finally:
            for f in logs:
                f.close()
        rows: list[dict[str, Any]] = []
        failed = []
        texts = [(folder / f"worker-{w[0]}" / "log.txt").read_text(errors="replace") for w in workers]
        for line in worker_warnings([f"{w[0] + 1}/{w[1]}" for w in workers], texts):
            log.warning("%s", line)
        for (shard, _, label, _), proc, text in zip(workers, procs, texts, strict=True):
            out = folder / f"worker-{shard}"
            if proc.returncode != 0:
                tail = [ln for ln in text.splitlines() if ln.strip()][-_TAIL_LINES:]
                failed.append(f"{label} exited {proc.returncode}: " + " | ".join(tail))
                continue
            rows += json.loads((out / "rows.json").read_text())
        if failed:
            raise TnfError(f"{stage} in {len(workers)} worker processes: " + "; ".join(failed))
        return rows


def worker_warnings(names: Sequence[str], logs: Sequence[str]) -> list[str]:
    """The warnings in the workers' ``logs`` (one text per worker, named by ``names``), each message once, in the
    order first logged: ``worker 1/2: MESSAGE``, or ``workers 1/2, 2/2: MESSAGE`` for one that several logged."""
    seen: dict[str, list[str]] = {}
    for name, text in zip(names, logs, strict=True):
        for line in text.splitlines():
            if "WARNING" in line:
                who = seen.setdefault(line.split(" - ", 1)[-1], [])
                if name not in who:
                    who.append(name)
    return [f"worker{'s' * (len(who) > 1)} {', '.join(who)}: {message}" for message, who in seen.items()]


def _wait(procs: list[Any], folder: Path, workers: Sequence[tuple[int, int, str, float]], tasks: list, p: Any) -> None:
    """Poll the workers until every one has exited, moving each one's bar to the steps it has written."""
    while True:
        running = [proc.poll() is None for proc in procs]
        for (shard, *_), task in zip(workers, tasks, strict=True):
            path = folder / f"worker-{shard}" / "progress"
            try:
                p.update(task, completed=float(path.read_text()))
            except (OSError, ValueError):
                pass
        if not any(running):
            return
        time.sleep(0.25)


def _stop(procs: list[Any], grace: float = 10.0) -> None:
    """Terminate the workers still running, waiting up to ``grace`` seconds before killing them."""
    for proc in procs:
        if proc.poll() is None:
            proc.terminate()
    deadline = time.monotonic() + grace
    for proc in procs:
        try:
            proc.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _worker(stage: str, config: str, shard: int, shards: int, out: str) -> int:
    """A worker's body: ``stage``'s ``worker_rows`` on its share; its rows to ``out/rows.json``."""
    _die_with_parent()
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][%(name)s][%(levelname)s] - %(message)s")
    import torch
    from omegaconf import OmegaConf

    torch.set_num_threads(int(os.environ.get(_THREADS_ENV, "1")))
    cfg = OmegaConf.load(config)
    cfg.shard, cfg.shards, cfg.progress = shard, shards, False
    module = importlib.import_module(f"tnf.stages.{stage.replace('-', '_')}")
    body: Callable[[Any, Any], list[dict[str, Any]]] = module.worker_rows
    try:
        rows = body(cfg, StepFile(Path(out) / "progress"))
    except TnfError as e:  # one line, as the tnf command prints it
        print(f"error: {e}", file=sys.stderr, flush=True)
        return 1
    write_json(Path(out) / "rows.json", rows)
    return 0


def _die_with_parent() -> None:
    """On Linux, have the kernel stop this worker when its parent dies (a SIGKILL or SIGTERM the parent could not
    pass on), so that no worker goes on writing into the store alone."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes
    import signal

    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


if __name__ == "__main__":
    stage_, config_, shard_, shards_, out_ = sys.argv[1:6]
    sys.exit(_worker(stage_, config_, int(shard_), int(shards_), out_))
