"""Names of model runs (``models/<run_name>/``): every run name tnf makes is made here.

``tnf pipeline`` names a model after its generator, dataset and seed (``model_run_name``; a sensor-transfer
model: ``transfer_run_name``); ``tnf train`` and ``tnf finetune`` run alone, without ``run_name``, use the
shorter ``train_run_name`` and ``finetune_run_name``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any


def dataset_label(name: Any) -> str:
    """A short label of a dataset name or path, for run names."""
    return Path(str(name)).name


def model_run_name(generator: str, dataset: str, seed: Any) -> str:
    """``<generator>-<dataset>-seed<k>``: one trained model per generator, dataset and seed."""
    return f"{generator}-{dataset}-seed{seed}"


def transfer_run_name(
    generator: str, dataset: str, checkpoint: Any, per_object: Any, extra_touches: Any, seed: Any
) -> str:
    """``<generator>-<dataset>-<from-RUN|scratch>-<n>pt[+<m>]-seed<k>`` for a sensor-transfer model: ``n`` touches
    per object (``all`` for None), ``m`` more in all (``extra_touches``; none when falsy). ``checkpoint`` is
    the source model's checkpoint (``RUN/FILE`` or a run name; None: trained from scratch)."""
    origin = f"from-{str(checkpoint).split('/')[0]}" if checkpoint else "scratch"
    per = per_object if per_object is not None else "all"
    extra = f"+{extra_touches}" if extra_touches else ""
    return f"{generator}-{dataset}-{origin}-{per}pt{extra}-seed{seed}"


def train_run_name(generator: str, datasets: Sequence[str]) -> str:
    """``<generator>_<dataset>``: ``tnf train``'s run without ``train.run_name``."""
    return f"{generator}_{dataset_label(datasets[0] if datasets else 'data')}"


def finetune_run_name(source_run: str | None, generator: str, datasets: Sequence[str]) -> str:
    """``<source run>_ft_<dataset>``, or ``scratch_<generator>_<dataset>`` without a source model:
    ``tnf finetune``'s run without ``finetune.run_name``."""
    label = dataset_label(datasets[0] if datasets else "data")
    return f"{source_run}_ft_{label}" if source_run is not None else f"scratch_{generator}_{label}"
