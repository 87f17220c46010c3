"""``tnf pipeline``: every stage in order for one experiment, from objects to the report.

(calibrate ->) capture -> fit-scene -> touch -> pair -> train (or finetune, for sensor transfer) -> generate ->
evaluate, each with the same composed config.
Each stage skips the items the artifact store already holds with a matching config, so re-running a finished
or interrupted pipeline only does what is missing. Each stage gets what the stages before it returned (the
model's run id, the folder of generated images; ``stage_config``). The model's run id is the one ``tnf train``
gives it (``tnf.generators.names``: generator option, dataset, seed and settings hash), so a pipeline after a
``tnf train`` with the same settings reuses its model, and a sweep (``tnf pipeline -m
generator=tn_cgan,lee,cyclegan seed=0,1,2``) trains one model per job and all jobs fill one report.
"""

from __future__ import annotations

import copy
import importlib
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tnf.artifacts import ArtifactStore, write_json
from tnf.registry import FROM_YAML, SettingError, from_dict, yaml_defaults
from tnf.runtime import resolve_device, stage_console

ORDER = ("calibrate", "capture", "fit-scene", "touch", "pair", "train", "finetune", "generate", "evaluate")


@dataclass
@yaml_defaults("pipeline/default")
class PipelineSettings:
    """The ``pipeline`` section: which stages ``tnf pipeline`` runs and how long they are expected to take."""

    stages: list[str] = FROM_YAML
    """Stages to run, names of ``ORDER``; they run in that order whatever the order given."""
    expected_s: dict[str, float] | None = FROM_YAML
    """Seconds each stage is expected to take, by stage name, for the estimate of the time left; null: none
    until a run of this experiment in the same store has finished (its times replace these)."""

    def validate(self) -> None:
        unknown = [s for s in self.stages if s not in ORDER]
        if unknown:
            raise SettingError("stages", f"unknown stage {unknown[0]!r}; stages: {', '.join(ORDER)}")
        if "train" in self.stages and "finetune" in self.stages:
            raise SettingError("stages", "give train (a new model) or finetune (sensor transfer), not both")
        for stage, seconds in (self.expected_s or {}).items():
            if seconds < 0:
                raise SettingError(f"expected_s.{stage}", f"must be >= 0, got {seconds}")

    def ordered(self) -> list[str]:
        """The stages to run, in pipeline order (``ORDER``)."""
        return [s for s in ORDER if s in self.stages]


def pipeline_settings(cfg: Any) -> PipelineSettings:
    """``cfg.pipeline`` validated into :class:`PipelineSettings`."""
    return from_dict(PipelineSettings, cfg.pipeline, where="pipeline")


def run(cfg: Any) -> dict[str, Any]:
    from omegaconf import OmegaConf

    console = stage_console()
    stages = pipeline_settings(cfg).ordered()
    cfg = copy.deepcopy(cfg)  # the caller's config stays as it was
    OmegaConf.resolve(cfg)
    # The model the generate and evaluate stages use: the one train or finetune returns; without either stage,
    # the model `tnf train` trains with this config.
    model = None if {"train", "finetune"} & set(stages) else _given_model(cfg)

    times: dict[str, float] = {}
    results: dict[str, Any] = {}
    expected = expected_times(cfg)
    t_all = time.perf_counter()
    for i, stage in enumerate(stages, 1):
        if stage == "evaluate":  # the report it writes shows this run's wall times so far
            _write_timings(cfg, model, times, None)
        left = time_left(stages[i - 1 :], times, expected)
        eta = f" · about {_clock(left)} left" if left is not None else ""
        so_far = _clock(time.perf_counter() - t_all)
        console.rule(f"[bold]pipeline {i}/{len(stages)}: {stage}[/] · {so_far} so far{eta}")
        module = importlib.import_module(f"tnf.stages.{stage.replace('-', '_')}")
        t0 = time.perf_counter()
        results[stage] = module.run(stage_config(cfg, stage, model, results.get("generate")))
        times[stage] = time.perf_counter() - t0
        if stage in ("train", "finetune"):
            model = str(results[stage]["run_name"])
    total = time.perf_counter() - t_all
    _summary(console, cfg, model, stages, times, total)
    return {"times": times, "total": total, "model": model}


def stage_config(cfg: Any, stage: str, model: str | None, generated: dict[str, Any] | None = None) -> Any:
    """The config ``stage`` runs with in the pipeline: ``cfg`` with what earlier stages returned filled in where
    ``cfg`` leaves it unset. ``generate`` and ``evaluate`` get the model (``generate.model``, ``evaluate.model``),
    ``evaluate`` the generated images (``evaluate.generated``: the folder ``generated`` returned by the generate
    stage names, else ``generate.run_name`` or the model) and the test dataset (``evaluate.dataset``: this
    config's paired dataset)."""
    from omegaconf import open_dict

    if stage not in ("generate", "evaluate"):
        return cfg
    out = copy.deepcopy(cfg)
    with open_dict(out):
        out.generate.model = out.generate.model or model
        if stage == "evaluate":
            images = Path(generated["run_dir"]).name if generated else out.generate.run_name or out.generate.model
            out.evaluate.model = out.evaluate.model or model
            out.evaluate.generated = out.evaluate.generated or images
            out.evaluate.dataset = out.evaluate.dataset or _dataset(out)
    return out


def _given_model(cfg: Any) -> str:
    """The model of ``cfg`` when the pipeline trains none: ``generate.model``, else the one ``tnf train``
    trains with ``cfg`` (``train.run_name`` or its run id)."""
    from tnf.stages.train import model_run

    return str(cfg.generate.model or model_run(cfg))


def expected_times(cfg: Any) -> dict[str, float]:
    """Seconds each stage is expected to take: the last finished run of this experiment in this store (its
    ``timings`` file), else the experiment's ``pipeline.expected_s`` (measured on 2 CPU cores), else none."""

    folder = ArtifactStore(cfg.data_root).path("reports", str(cfg.evaluate.name), "timings")
    done = []
    for path in folder.glob("*.json") if folder.is_dir() else []:
        try:
            record = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        if isinstance(record, dict) and record.get("total_s") and isinstance(record.get("stages"), dict):
            done.append((path.stat().st_mtime, record["stages"]))
    if done:
        return {str(k): float(v) for k, v in max(done, key=lambda d: d[0])[1].items()}
    return {str(stage): seconds for stage, seconds in (pipeline_settings(cfg).expected_s or {}).items()}


def time_left(todo: list[str], done: dict[str, float], expected: dict[str, float]) -> float | None:
    """Seconds left for the stages ``todo``: their expected times, scaled by how the stages ``done`` so far
    compared with theirs. Stages expected to take under 10 s (too short to time the machine) and stages that took
    under a quarter of their expected time (work the store already held) do not set the scale. None when a stage
    to do has no expected time."""
    if any(s not in expected for s in todo):
        return None
    ran = [s for s in done if s in expected and expected[s] >= 10 and done[s] >= 0.25 * expected[s]]
    scale = sum(done[s] for s in ran) / sum(expected[s] for s in ran) if ran else 1.0
    return scale * sum(expected[s] for s in todo)


def _clock(seconds: float) -> str:
    """``m:ss`` (``h:mm:ss`` from an hour)."""
    m, s = divmod(round(seconds), 60)
    h, m = divmod(m, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


def _dataset(cfg: Any) -> str:
    """The name ``tnf pair`` gives the dataset of this config."""
    from tnf.data.store import dataset_name

    return dataset_name(cfg.pair, str(cfg.sensor.name), str(cfg.scene.name))


def _summary(
    console: Any, cfg: Any, model: str | None, stages: list[str], times: dict[str, float], total: float
) -> None:
    from rich.table import Table

    table = Table(title="pipeline stages", header_style="bold")
    table.add_column("stage")
    table.add_column("wall time", justify="right")
    for s in stages:
        table.add_row(s, f"{times[s]:.1f} s")
    table.add_row("[bold]total", f"[bold]{total:.1f} s")
    console.print(table)
    report = _write_timings(cfg, model, times, total)
    if (report / "report.md").is_file():
        if "evaluate" in stages:
            console.print(f"report: [bold]{report / 'report.md'}[/]")
        else:  # the report there is an earlier run's: this one did not evaluate
            console.print(f"report (not updated: evaluate did not run): {report / 'report.md'}")


def _write_timings(cfg: Any, model: str | None, times: dict[str, float], total: float | None) -> Any:
    """``<report>/timings/<model>.json``: this run's wall time per stage (the stages run so far; ``total_s`` once
    all have run), which the report shows; nothing without a model. Returns the report's folder."""

    report = ArtifactStore(cfg.data_root).path("reports", str(cfg.evaluate.name))
    if model is None:
        return report
    device = resolve_device(str(cfg.device))
    write_json(
        report / "timings" / f"{model}.json",
        {"stages": times, "total_s": total, "device": device, "model": model},
    )
    return report
