"""Mean and standard error over seeds, and collecting per-run results (one evaluated model each) into tables.

A run's results JSON (written by ``tnf evaluate`` for one model, see ``tnf.eval.run``)::

    {"schema": 1, "table": "main" | "transfer", "method": "T-N", "seed": 0, "model": "...",
     "image": {test_set: {method_or_"BG": {"ssim": float, "mse": float, "n": int,
                                           "per_object": {object: {"ssim", "mse", "n"}}}}},
     "accuracy": {"Sim": percent, "Sim + T-N": percent, "T-N only": percent},
     "environment": {"accelerator", "cpu_cores", "python", "torch", "warp", "lightning", "tnf", "commit", ...},
     "evaluate_s": seconds, "phases_s": {phase: seconds}}

``environment`` (``tnf.runtime.environment``) and ``evaluate_s`` are absent from runs evaluated before they were
recorded; the report then says ``not recorded``. ``phases_s`` (``tnf.eval.timing``; not in the report) splits the
evaluation's wall time into its phases (``tnf.eval.run.evaluate_model`` names them; ``write`` and ``report`` last).

Test set ``all`` holds the pooled ``BG`` row. Rows shared by several runs of the same seed (``Sim``, ``BG``: every
generator's job of seed 0 computes the same ones) are averaged within the seed first, so each seed counts once;
the standard error is then over seeds: ``std(ddof=1) / sqrt(k)`` (0 for a single seed).
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tnf.artifacts import read_json
from tnf.errors import TnfError

RESULTS_FILE = "results.json"
SCHEMA = 1


@dataclass(frozen=True)
class Stat:
    """A mean over ``n`` seeds and its standard error."""

    mean: float
    se: float
    n: int


def mean_se(values: Sequence[float]) -> Stat:
    """Mean and standard error of the mean (sample std with ddof=1 over sqrt(n); 0 when n == 1)."""
    vals = [float(v) for v in values]
    if not vals:
        raise ValueError("mean_se of no values")
    n = len(vals)
    m = sum(vals) / n
    if n == 1:
        return Stat(m, 0.0, 1)
    var = sum((v - m) ** 2 for v in vals) / (n - 1)
    return Stat(m, math.sqrt(var / n), n)


def over_seeds(pairs: Iterable[tuple[int, float]]) -> Stat:
    """``(seed, value)`` pairs -> Stat over seeds, values of the same seed averaged first."""
    by_seed: dict[int, list[float]] = defaultdict(list)
    for seed, v in pairs:
        by_seed[int(seed)].append(float(v))
    return mean_se([sum(v) / len(v) for _, v in sorted(by_seed.items())])


def find_results(folder: str | Path) -> list[Path]:
    """Every ``results.json`` below ``folder`` (a Hydra sweep folder, or a report's ``runs/`` folder)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise TnfError(f"results folder not found: {folder}")
    return sorted(p for p in folder.rglob(RESULTS_FILE) if not any(part.startswith(".") for part in p.parts[-3:]))


def load_results(paths: Iterable[str | Path]) -> list[dict[str, Any]]:
    """Read and check results JSON files; each gets a ``_path`` key (where it was read from)."""
    out = []
    for p in paths:
        r = read_json(p, "results file")
        if not isinstance(r, dict) or r.get("schema") != SCHEMA or "method" not in r or "seed" not in r:
            raise TnfError(f"results file {p} is not a tnf evaluate results file (schema {SCHEMA})")
        r["_path"] = str(p)
        out.append(r)
    return out


@dataclass
class TableData:
    """Aggregated numbers of one table (``main`` = the paper's Table 1, ``transfer`` = its Table 2)."""

    image: dict[tuple[str, str], dict[str, Stat]]
    """(test_set, method) -> {"ssim": Stat, "mse": Stat}; method ``BG`` is the background baseline."""
    per_object: dict[tuple[str, str], dict[str, Stat]]
    """(test_set, method) -> object -> SSIM Stat."""
    accuracy: dict[str, Stat]
    """Training-set row ("Sim", "Sim + T-N", "T-N only") -> accuracy Stat in percent."""
    methods: list[str]
    """Methods in the order first seen."""
    runs: list[dict[str, Any]]
    """The runs that went in."""


def aggregate(results: Sequence[dict[str, Any]]) -> dict[str, TableData]:
    """Per-run results -> {table name: TableData}, over seeds."""
    grouped: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for r in results:
        grouped[r.get("table", "main")].append(r)
    return {table: _aggregate_table(runs) for table, runs in grouped.items()}


def _aggregate_table(runs: Sequence[dict[str, Any]]) -> TableData:
    image: dict[tuple[str, str, str], list[tuple[int, float]]] = defaultdict(list)
    per_obj: dict[tuple[str, str, str], list[tuple[int, float]]] = defaultdict(list)
    acc: dict[str, list[tuple[int, float]]] = defaultdict(list)
    methods: list[str] = []
    for r in runs:
        seed = int(r["seed"])
        if r["method"] not in methods:
            methods.append(r["method"])
        for test_set, rows in (r.get("image") or {}).items():
            for method, m in rows.items():
                for metric in ("ssim", "mse"):
                    if m.get(metric) is not None:
                        image[(test_set, method, metric)].append((seed, m[metric]))
                for obj, om in (m.get("per_object") or {}).items():
                    per_obj[(test_set, method, obj)].append((seed, om["ssim"]))
        for row, v in (r.get("accuracy") or {}).items():
            acc[row].append((seed, v))
    image_out: dict[tuple[str, str], dict[str, Stat]] = defaultdict(dict)
    for (test_set, method, metric), pairs in image.items():
        image_out[(test_set, method)][metric] = over_seeds(pairs)
    per_obj_out: dict[tuple[str, str], dict[str, Stat]] = defaultdict(dict)
    for (test_set, method, obj), pairs in sorted(per_obj.items()):
        per_obj_out[(test_set, method)][obj] = over_seeds(pairs)
    return TableData(
        image=dict(image_out),
        per_object=dict(per_obj_out),
        accuracy={row: over_seeds(p) for row, p in acc.items()},
        methods=methods,
        runs=list(runs),
    )
