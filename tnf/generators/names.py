"""Names of model runs (``models/<run id>/``): every run id tnf makes is made here, by ``run_id``.

A run id is ``<option>-<dataset>-seed<k>-<hash>``:

- ``option``: the generator config option the run was composed with (``tn_cgan``, ``tn_cgan_press``, ``lee``:
  Hydra's ``hydra.runtime.choices.generator``), or the generator's registered name where no Hydra job runs (a
  config composed in a test or loaded from a file). A fine-tuned model adds ``+<transfer option>`` (``+tn``,
  ``+real``), or ``+ft`` without one.
- ``dataset``: the short label of the first training dataset (``digit-hashgrid``).
- ``k``: the run's seed.
- ``hash``: the first ``HASH_CHARS`` hex digits of the hash of the settings that define the model, the same
  settings whose hash decides whether a finished run is skipped (``tnf.stages.train.run_config``), so the id
  and the skip-or-redo key agree.

``tnf train``, ``tnf finetune``, ``tnf pipeline`` and ``tnf generate`` name the model of a config the same way;
``train.run_name`` and ``finetune.run_name`` replace the id. The id without its hash, ``run_family``, names
the runs of one option, dataset and seed; ``find_run`` finds the one finished run a family name stands for.
"""

from __future__ import annotations

import glob
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from tnf.artifacts import MANIFEST, config_hash
from tnf.errors import TnfError

HASH_CHARS = 8
"""Hex digits of the settings hash at the end of a run id."""


def dataset_label(name: Any) -> str:
    """A short label of a dataset name or path, for run ids."""
    return Path(str(name)).name


def chosen_option(group: str) -> str | None:
    """The config option of ``group`` the running Hydra job was composed with (``hydra.runtime.choices``);
    None outside a Hydra job or when the group has no choice."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return None
    choice = HydraConfig.get().runtime.choices.get(group)
    return str(choice) if choice not in (None, "null", "none") else None


def generator_option(registered: str) -> str:
    """The generator's part of a run id: the chosen ``generator`` option when it is ``registered`` or one of
    its variants (``tn_cgan_press`` for ``tn_cgan``), else the registered name ``registered``."""
    choice = chosen_option("generator")
    if choice is not None and (choice == registered or choice.startswith(f"{registered}_")):
        return choice
    return registered


def finetune_option(registered: str) -> str:
    """The option part of a fine-tuned model's run id: ``<generator option>+<transfer option>``, or
    ``<generator option>+ft`` without a chosen transfer."""
    return f"{generator_option(registered)}+{chosen_option('transfer') or 'ft'}"


def run_family(option: str, dataset: Any, seed: Any) -> str:
    """``<option>-<dataset label>-seed<k>``: a run id without its settings hash."""
    return f"{option}-{dataset_label(dataset)}-seed{seed}"


def run_id(option: str, dataset: Any, seed: Any, config: Mapping[str, Any]) -> str:
    """``<option>-<dataset label>-seed<k>-<hash>``: the run id of a model whose defining settings are
    ``config`` (the dict whose ``tnf.artifacts.config_hash`` the run's manifest records)."""
    return f"{run_family(option, dataset, seed)}-{config_hash(config)[:HASH_CHARS]}"


def find_run(models: Path, name: str) -> str | None:
    """The run folder under ``models`` that ``name`` stands for: ``name`` itself when that folder exists, else the
    one finished run (a folder with a manifest) of the family ``name`` (``run_family``); None when there is none.
    A family with several finished runs is a TnfError that lists them."""
    if (models / name).is_dir():
        return name
    pattern = re.compile(rf"{re.escape(name)}-[0-9a-f]{{{HASH_CHARS}}}")
    runs = models.glob(f"{glob.escape(name)}-*") if models.is_dir() else []
    found = sorted(p.name for p in runs if pattern.fullmatch(p.name) and (p / MANIFEST).is_file())
    if len(found) > 1:
        raise TnfError(f"{name} stands for several finished runs under {models}: {', '.join(found)}; name one")
    return found[0] if found else None
