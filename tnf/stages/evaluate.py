"""``tnf evaluate``: score a trained generator and write the report.

For one model (``evaluate.model=RUN``): SSIM and MSE of its generated images against ground truth on each test
split (plus the BG row, the sensor's background used as the prediction), per object too, and the classification
task (rows Sim, Sim + G, G only). The run's results go to ``<root>/reports/<name>/runs/<table>_<method>_seed<k>/``
(and to the Hydra job's output folder); then the report in ``<root>/reports/<name>/`` is rebuilt from every run
there. ``evaluate.sweep_dir=DIR`` instead collects the results.json files of a Hydra multirun folder.
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any, cast

from tnf.artifacts import ArtifactStore, config_hash, exclusive, write_bytes, write_json
from tnf.errors import TnfError
from tnf.eval.aggregate import RESULTS_FILE, find_results, load_results
from tnf.eval.paper import METHOD_LABELS
from tnf.eval.run import EvalJob, check_not_another_models, collect_sweep, evaluate_model, run_id
from tnf.eval.settings import EvaluateSettings
from tnf.eval.timing import Phases, phases_line
from tnf.registry import from_dict
from tnf.stages.settings import identity_config


def run(cfg: Any) -> dict[str, Any]:
    from omegaconf import OmegaConf

    from tnf.eval.report import write_report
    from tnf.runtime import stage_console

    console = stage_console()
    ecfg = from_dict(EvaluateSettings, cfg.evaluate, where="evaluate")
    store = ArtifactStore(cfg.data_root)
    report_dir = store.path("reports", ecfg.name)
    runs_dir = report_dir / "runs"
    out: dict[str, Any] = {}
    force = ecfg.force
    timer: Phases | None = None  # this run's phases (None when no model is evaluated)
    folder = None

    if not ecfg.model and not ecfg.sweep_dir:
        from tnf.stages.train import model_run

        trained = model_run(cfg)  # the model `tnf train` trains with these settings, as `tnf generate` takes
        if store.manifest("models", trained) is not None:
            console.print(f"evaluate.model not set: the model trained with these settings, {trained}")
            ecfg = dataclasses.replace(ecfg, model=trained)

    if ecfg.sweep_dir:
        n = collect_sweep(ecfg.sweep_dir, runs_dir, force)
        console.print(f"collected {n} run(s) from {ecfg.sweep_dir}")

    if ecfg.model:
        method = ecfg.method or _method_label(cfg)
        settings = cast(dict[str, Any], OmegaConf.to_container(cfg, resolve=True))
        # Everything that changes the numbers (a store that is moved or mounted elsewhere keeps its results).
        chash = config_hash(identity_config(cfg))
        folder = runs_dir / run_id({"table": ecfg.table, "method": method, "seed": cfg.seed})
        old = folder / RESULTS_FILE
        replaced = check_not_another_models(old, str(ecfg.model), method, cfg.seed, force, store.path("models"))
        if replaced:
            console.print(replaced, markup=False)
        if not force and old.is_file() and load_results([old])[0].get("config_hash") == chash:
            console.print(
                f"{method} seed {cfg.seed}: results exist with the same settings, skipped (evaluate.force=true)"
            )
            results = load_results([old])[0]
            results.pop("_path")
        else:
            timer = Phases(str(cfg.device))
            results, examples_png, figures = evaluate_model(_job(cfg, ecfg, settings, method), store, timer)
            results["config_hash"] = chash
            # Again: a job beside this one (a sweep, parallel runs) may have written this row meanwhile. Nothing
            # of this run is in the row's folder until here, so a refused run leaves the other model's intact.
            check_not_another_models(old, str(ecfg.model), method, cfg.seed, force, store.path("models"))
            with timer.phase("write"):
                if examples_png is not None:
                    write_bytes(folder / str(results["examples"]), examples_png)
                for file, png in figures.items():
                    write_bytes(folder / file, png)
                write_json(folder / RESULTS_FILE, results)
        out["results"] = results

    # Jobs of a sweep rebuild the same report, each from every run present: one at a time (tnf.artifacts.exclusive),
    # so that a job that listed the runs before another job's run was written cannot write its report last.
    nothing = TnfError(
        f"nothing to report in {report_dir}: give evaluate.model=RUN (a folder under {store.path('models')}) "
        "or evaluate.sweep_dir=DIR"
    )
    if not runs_dir.is_dir():
        raise nothing
    with exclusive(report_dir):
        files = find_results(runs_dir)
        if not files:
            raise nothing
        t0 = time.perf_counter()
        tables = write_report(
            load_results(files), report_dir, name=ecfg.name, notes=ecfg.notes or None, next_step=ecfg.next or None
        )
        if timer is not None and folder is not None:
            # The report's seconds join the run's record (which the report does not show), written again.
            timer.add("report", time.perf_counter() - t0)
            out["results"]["phases_s"] = {**out["results"].get("phases_s", {}), **timer.record()}
            write_json(folder / RESULTS_FILE, out["results"])
    if folder is not None:
        _copy_to_hydra_output(folder)
    _print_summary(console, tables, report_dir)
    if timer is not None:
        console.print(phases_line(out["results"]["phases_s"]))
    out["report"] = report_dir / "report.md"
    out["tables"] = tables
    return out


def _method_label(cfg: Any) -> str:

    name = str(cfg.generator.name) if "generator" in cfg and "name" in cfg.generator else "G"
    return METHOD_LABELS.get(name, name)


def _job(cfg: Any, ecfg: EvaluateSettings, settings: dict[str, Any], method: str) -> Any:
    """The evaluation of ``evaluate.model`` (``ecfg``: the ``evaluate`` section; ``settings``: the whole config as
    plain data)."""

    from tnf.stages.train import dataset_names

    datasets = dataset_names(cfg)  # an unset name is the dataset `tnf pair` builds with cfg, as train takes it
    return EvalJob(
        settings=ecfg,
        method=method,
        seed=int(cfg.seed),
        device=str(cfg.device),
        progress=bool(cfg.progress),
        data_root=str(cfg.data_root),
        generator=str(cfg.generator.name) if "generator" in cfg else None,
        datasets=datasets,
        mirror_average=bool(cfg.generate.mirror_average),
        touch_force=float(cfg.touch.force),
        sensor=str(cfg.sensor.name),
        objects=settings["objects"],
        object_names=[str(o) for o in cfg.object_names] if cfg.object_names else None,
        simulator=settings["simulator"],
    )


def _copy_to_hydra_output(folder: Path) -> None:
    """Put the run's results into the Hydra job folder too, so a multirun folder can be aggregated later."""
    from hydra.core.hydra_config import HydraConfig
    from omegaconf.errors import OmegaConfBaseException

    try:
        out = Path(HydraConfig.get().runtime.output_dir)
    except (ValueError, OmegaConfBaseException):  # not inside a Hydra app that has a run folder (tests, API use)
        return
    for f in folder.iterdir():
        if f.is_file():
            shutil.copyfile(f, out / f.name)


def _seeds(stats: Mapping[str, Any]) -> str:
    """'seeds: T-N 3, BG 3': how many seeds each row of ours averages (a row's first statistic), printed under a table.
    A sweep's jobs print the report as it stood when each wrote it, so a job's table may hold fewer seeds."""
    counts = {row: st.n for row, st in stats.items() if st is not None}
    return "seeds: " + ", ".join(f"{row} {n}" for row, n in counts.items()) if counts else ""


def _print_summary(console: Any, tables: Mapping[str, Any], report_dir: Path) -> None:
    from rich.table import Table

    from tnf.eval.report import TABLES, accuracy_rows, against_paper, checks, fmt_stat, image_rows, verdict

    console.print(verdict(dict(tables)).replace("**", ""))
    for name, data in tables.items():
        num = TABLES.get(name, (name,))[0]
        rows = image_rows(name, data)
        t = Table(title=f"Table {num}a", box=None)
        for col in ("test set", "method", "SSIM", "paper", "MSE", "paper"):
            t.add_column(col)
        for r in rows:
            o, p = r["ours"], r["paper"]
            t.add_row(
                r["test_set"],
                r["method"],
                fmt_stat(o.get("ssim"), "ssim"),
                fmt_stat(p.get("ssim"), "ssim"),
                fmt_stat(o.get("mse"), "mse"),
                fmt_stat(p.get("mse"), "mse"),
            )
        console.print(t)
        console.print(_seeds({r["method"]: r["ours"].get("ssim") for r in rows}))
        rows = accuracy_rows(name, data)
        t = Table(title=f"Table {num}b", box=None)
        for col in ("training set", "accuracy %", "paper"):
            t.add_column(col)
        for r in rows:
            t.add_row(r["row"], fmt_stat(r["ours"], "acc"), fmt_stat(r["paper"], "acc"))
        console.print(t)
        console.print(_seeds({r["row"]: r["ours"] for r in rows}))
        failed = [c for c, v, _ in checks(name, data) if v.startswith("FAILS")]
        if failed:
            console.print(f"[yellow]claims not reproduced:[/] {'; '.join(failed)}")
        short = [c for c, v, _ in against_paper(name, data) if v == "FALLS SHORT"]
        if short:
            console.print(f"[yellow]below the paper's figures:[/] {'; '.join(short)}")
    console.print(f"report: {report_dir / 'report.md'}")
