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
the runs of one option, dataset and seed; ``find_run`` finds the one finished run a family name stands for, and
``new_run_note`` tells how a new run's settings differ from its family's latest run (``settings_diff``).
"""

from __future__ import annotations

import glob
import json
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from tnf.artifacts import MANIFEST, config_hash, identity
from tnf.errors import TnfError

HASH_CHARS = 8

#: Each run folder's record of the settings it was started with (``{"config", "config_hash"}``).
RUN_FILE = "run.json"
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


def settings_diff(old: Mapping[str, Any], new: Mapping[str, Any], limit: int = 4) -> str:
    """The settings that differ from ``old`` to ``new`` (nested dicts, compared by dotted key), as
    ``key: old -> new`` joined by ``; `` in key order, the first ``limit`` of them then ``and N more``; a key only
    one of them has is ``unset`` in the other. Empty when they agree."""

    def flat(d: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
        out: dict[str, Any] = {}
        for k, v in d.items():
            key = f"{prefix}{k}"
            out.update(flat(v, f"{key}.") if isinstance(v, Mapping) and v else {key: v})
        return out

    def show(d: dict[str, Any], key: str) -> str:
        return json.dumps(d[key], default=str) if key in d else "unset"

    a, b = flat(old), flat(new)
    keys = sorted(k for k in a.keys() | b.keys() if k not in a or k not in b or a[k] != b[k])
    shown = [f"{k}: {show(a, k)} -> {show(b, k)}" for k in keys[:limit]]
    more = [f"and {len(keys) - limit} more"] if len(keys) > limit else []
    return "; ".join(shown + more)


def new_run_note(models: Path, name: str, config: Mapping[str, Any]) -> str | None:
    """For the run id ``name`` whose folder under ``models`` does not exist yet, with settings ``config``: ``a new
    run: <run> has other settings (...)`` naming the latest run of its family (``run_family``; by the time of its
    ``run.json``) and the settings that differ (``settings_diff``); None when there is none. A run whose
    ``run.json`` is unreadable is passed over."""
    family, _, digits = name.rpartition("-")
    if (models / name).exists() or not re.fullmatch(rf"[0-9a-f]{{{HASH_CHARS}}}", digits) or not models.is_dir():
        return None
    pattern = re.compile(rf"{re.escape(family)}-[0-9a-f]{{{HASH_CHARS}}}")
    runs = [p / RUN_FILE for p in models.glob(f"{glob.escape(family)}-*") if pattern.fullmatch(p.name)]
    for run_file in sorted((f for f in runs if f.is_file()), key=lambda f: f.stat().st_mtime_ns, reverse=True):
        try:
            old = json.loads(run_file.read_text())["config"]
        except (OSError, ValueError, TypeError, KeyError):
            continue
        if isinstance(old, Mapping) and (diff := settings_diff(old, identity(config))):
            return f"a new run: {run_file.parent.name} has other settings ({diff})"
    return None


def require_checkpoint(path: Path, setting: str) -> Path:
    """``path``, a model run's checkpoint, when it exists; else a one-line TnfError naming how to make it and
    ``setting`` (``generate.model``, ``evaluate.model``), the setting that chose it."""
    if not path.is_file():
        raise TnfError(
            f"checkpoint not found: {path}; train it with `tnf train` (train.force=true trains it again) or check "
            f"{setting}/checkpoint"
        )
    return path
