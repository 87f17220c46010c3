"""Wall seconds of the phases of ``tnf evaluate``, recorded into each run's results (``phases_s``).

``Phases.phase(name)`` adds the seconds its block takes to ``name`` (a phase entered again accumulates). On a CUDA
device each boundary synchronises once, so that the GPU's queued work is counted in the phase that queued it.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import Any


class Phases:
    """Seconds per phase, in the order the phases first ran."""

    def __init__(self, device: str | None = None):
        self.seconds: dict[str, float] = {}
        self._cuda = device is not None and str(device).startswith("cuda")

    def _sync(self) -> None:
        if self._cuda:
            import torch

            torch.cuda.synchronize()

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        self._sync()
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self._sync()
            self.add(name, time.perf_counter() - t0)

    def add(self, name: str, seconds: float) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds

    def record(self) -> dict[str, float]:
        """The phases' seconds (rounded to milliseconds) for the results file."""
        return {k: round(v, 3) for k, v in self.seconds.items()}


def phases_line(phases: Mapping[str, Any]) -> str:
    """One line: ``evaluate phases (s): setup 0.0, load_model 1.2, novel_view.data 3.4, ... | sum 12.3``."""
    cells = ", ".join(f"{k} {float(v):.1f}" for k, v in phases.items())
    return f"evaluate phases (s): {cells} | sum {sum(float(v) for v in phases.values()):.1f}"
