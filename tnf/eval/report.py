"""The evaluation report: Markdown and CSV tables laid out like the paper's Tables 1 and 2, figures, checks.

``write_report(results, folder)`` aggregates per-run results over seeds and writes into ``folder``:

- ``report.md``: everything below, readable as plain text;
- ``table1a_image.csv`` / ``table1b_accuracy.csv`` (main experiment), ``table2a_image.csv`` /
  ``table2b_accuracy.csv`` (sensor transfer), each with our mean, standard error and seed count beside the
  paper's mean and standard error;
- ``ssim_per_object_<table>.png``: SSIM per object and method;
- the ``checks`` section: whether the paper's qualitative claims hold in our numbers;
- the ``against the paper`` section: whether our method (T-N and its variants) reaches the paper's own figures,
  beside BG's row in both (how far the two simulators' touches differ), and the experiment's ``notes``.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tnf.artifacts import write_bytes
from tnf.eval.aggregate import TableData, aggregate
from tnf.eval.claims import (
    against_paper,
    checks,
    verdict,
)
from tnf.eval.figures import bar_plot, line_plot
from tnf.eval.force_report import force_section
from tnf.eval.paper import PAPER
from tnf.eval.scoring import BG
from tnf.eval.tables import (
    TABLES,
    TEST_SET_NAMES,
    accuracy_rows,
    csv_bytes,
    fmt_stat,
    image_rows,
    ordered_methods,
    paper_cells,
    stat_cells,
)

# The tables' and the claims' names stay importable from here.
__all__ = [
    "TABLES",
    "TEST_SET_NAMES",
    "accuracy_rows",
    "against_paper",
    "checks",
    "fmt_stat",
    "image_rows",
    "render_markdown",
    "verdict",
    "write_report",
]


def batch_sampling(runs: Sequence[dict[str, Any]]) -> str | None:
    """How the rows that add generated images drew their batches (``evaluate.classifier.real_fraction``)."""
    fractions = {r["classify"].get("real_fraction") for r in runs if isinstance(r.get("classify"), dict)}
    if not fractions:
        return None
    if len(fractions) > 1:
        shown = ", ".join("uniform" if f is None else f"{f:g}" for f in sorted(fractions, key=lambda f: f or 0))
        return f"**The runs drew their batches differently** (real_fraction: {shown}); their rows do not compare."
    (f,) = fractions
    if f is None:
        return "Rows that add generated images draw each batch uniformly from all their images."
    return f"Rows that add generated images draw {f:.0%} of each batch from the ground-truth touches."


def generated_poses(runs: Sequence[dict[str, Any]]) -> str | None:
    """Where the generated touches of the classification rows came from (``generate.directions``), as their
    manifests record it; None when a run does not record it."""
    sources = [r["classify"].get("generated_poses") for r in runs if isinstance(r.get("classify"), dict)]
    if not sources or None in sources:
        return None
    if len({json.dumps(p, sort_keys=True) for p in sources}) > 1 or sources[0]["directions"] == "mixed":
        return (
            "**The generated touches come from different poses** in different runs or objects; the rows do not compare."
        )
    p = sources[0]
    if p["directions"] == "novel_view":
        axis = ", ".join(f"{a:g}" for a in p["cone_axis"])
        return (
            f"The generated touches come from inside the held-out cone ({p['cone_deg']:g} degrees about [{axis}], "
            "`generate.directions=novel_view`): the views that no Sim touch comes from, which the novel-view test "
            "touches come from."
        )
    return {
        "sphere": "The generated touches come from poses uniform over every direction (`generate.directions=sphere`).",
        "file": "The generated touches come from a file of poses (`generate.poses_file`).",
        "sim": "The generated touches take the poses of the simulated touches.",
    }.get(p["directions"])


def _seconds(t: float | None) -> str:
    return "-" if t is None else (f"{t:.1f}" if t < 100 else f"{t:.0f}")


def wall_times(timings: Sequence[dict[str, Any]], runs: Sequence[dict[str, Any]]) -> list[str]:
    """Markdown lines: the wall time of each stage of each model's last ``tnf pipeline`` run (``timings``: the
    ``timings/<model>.json`` files the pipeline writes, stages in the order they ran); evaluate's from the run's
    results where the pipeline had not recorded it yet (it writes the report while it runs)."""
    if not timings:
        return []
    evaluated = {r.get("model"): r.get("evaluate_s") for r in runs}
    rows = []
    for t in sorted(timings, key=lambda t: str(t.get("model"))):
        stages = dict(t.get("stages") or {})
        if "evaluate" not in stages and evaluated.get(t.get("model")) is not None:
            stages["evaluate"] = evaluated[t.get("model")]
        rows.append((str(t.get("model")), str(t.get("device", "-")), stages))
    shown = list(dict.fromkeys(s for _, _, stages in rows for s in stages if s != "evaluate"))
    shown += ["evaluate"] if any("evaluate" in stages for _, _, stages in rows) else []
    lines = [
        "### Wall times (seconds)",
        "",
        "Each model's last `tnf pipeline` run, stage by stage; a stage that found its work done takes next to no "
        "time (in a sweep whose seeds share one dataset, `data_seed`, the stages before training run in the first "
        "job). Evaluate: the evaluation that made "
        "the run's results.",
        "",
        "| Model | device | " + " | ".join(shown) + " | total |",
        "|---|---|" + "---|" * (len(shown) + 1),
    ]
    for model, device, stages in rows:
        cells = [_seconds(stages.get(s)) for s in shown]
        lines.append(f"| {model} | {device} | " + " | ".join(cells) + f" | {_seconds(sum(stages.values()))} |")
    return [*lines, ""]


def environments(runs: Sequence[dict[str, Any]]) -> list[str]:
    """Markdown lines: where the runs were evaluated (``tnf.runtime.environment``), one row per distinct
    environment with the runs it made."""
    keys = ("accelerator", "cpu_cores", "python", "torch", "warp", "lightning", "tnf", "commit")
    groups: dict[tuple[Any, ...], list[str]] = {}
    for r in sorted(runs, key=lambda r: (r.get("table", "main"), r["method"], r["seed"])):
        env = r.get("environment") or {}
        key = tuple(env.get(k) for k in keys)
        groups.setdefault(key, []).append(f"{r['method']} seed {r['seed']}")
    if not any(r.get("environment") for r in runs):
        return []
    lines = [
        "### Environment",
        "",
        "| Runs | accelerator | CPU cores | Python | torch | warp | lightning | tnf |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for key, names in groups.items():
        env = dict(zip(keys, key, strict=True))
        if not any(v is not None for v in key):
            lines.append(f"| {', '.join(names)} | not recorded | | | | | | |")
            continue
        version = env["tnf"] or "-"
        if env["commit"]:
            version += f" ({env['commit']})"
        cells = [env[k] if env[k] is not None else "-" for k in keys[:-2]]
        lines.append(f"| {', '.join(names)} | " + " | ".join(str(c) for c in cells) + f" | {version} |")
    return [*lines, ""]


def render_markdown(
    name: str,
    tables: dict[str, TableData],
    figures: dict[str, list[tuple[str, str]]],
    notes: str | None = None,
    timings: Sequence[dict[str, Any]] = (),
    next_step: str | None = None,
) -> str:
    """The report as Markdown; ``figures[table]`` lists (caption, relative path) of its PNGs; ``timings`` are the
    pipeline's wall times per model (see ``wall_times``); ``notes`` (the experiment's own words, e.g. why a
    figure falls short of the paper's) end it; ``next_step`` (what to run next) ends the opening verdict."""
    n_runs = sum(len(t.runs) for t in tables.values())
    lines = [
        f"# tnf evaluation report: {name}",
        "",
        verdict(tables, next_step),
        "",
        f"Written {time.strftime('%Y-%m-%d %H:%M')} from {n_runs} evaluated run(s). Every number is the mean ± "
        "standard error over seeds (column `seeds`; one seed: its value alone); the paper's figures are beside "
        "ours. SSIM (Gaussian window 11, sigma 1.5, data range 255, mean over RGB) and MSE (0-255 scale) on 8-bit "
        "images at 128 x 128. "
        "BG: the sensor's background image used as the prediction.",
        "",
    ]
    for table in sorted(tables, key=lambda t: (t not in TABLES, t)):
        lines += _table_section(table, tables[table], figures.get(table, []))
    runs = [r for t in tables.values() for r in t.runs]
    where = wall_times(timings, runs) + environments(runs)
    if where:
        lines += ["## Where and how long", "", *where]
    if notes and notes.strip():
        lines += ["## Notes", "", notes.strip(), ""]
    return "\n".join(lines)


def _table_section(table: str, data: TableData, figures: Sequence[tuple[str, str]]) -> list[str]:
    """Markdown lines of one table's section: its image metrics (a), its classification accuracy (b), its
    ``figures`` (caption, relative path), the paper's claims checked and its runs."""
    num, title = TABLES.get(table, (table, table))
    lines = [f"## Table {num}: {title}", "", *_image_table(num, table, data), *_accuracy_table(num, table, data)]
    for caption, path in figures:
        lines += [f"**{caption}**", "", f"![{caption}]({path})", ""]
    lines += _claims_section(num, table, data)
    lines += ["", f"### Runs (Table {num})", "", "| Method | Seed | Model | Results |", "|---|---|---|---|"]
    for run in sorted(data.runs, key=lambda r: (r["method"], r["seed"])):
        lines.append(f"| {run['method']} | {run['seed']} | {run.get('model') or '-'} | {run.get('_rel', '')} |")
    lines.append("")
    return lines


def _image_table(num: str, table: str, data: TableData) -> list[str]:
    """Markdown lines of table ``num``a: SSIM and MSE per test set and method, ours beside the paper's."""
    lines = [f"### Table {num}a: image metrics against ground truth", ""]
    lines += [
        "| Test set | Method | SSIM ↑ (ours) | SSIM (paper) | MSE ↓ (ours) | MSE (paper) | seeds |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in image_rows(table, data):
        o, p = r["ours"], r["paper"]
        n = max((s.n for s in o.values()), default=0)
        cells = [
            TEST_SET_NAMES.get(r["test_set"], r["test_set"]),
            r["method"],
            fmt_stat(o.get("ssim"), "ssim"),
            fmt_stat(p.get("ssim"), "ssim"),
            fmt_stat(o.get("mse"), "mse"),
            fmt_stat(p.get("mse"), "mse"),
            str(n or "-"),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _accuracy_table(num: str, table: str, data: TableData) -> list[str]:
    """Markdown lines of table ``num``b: classification accuracy (%) per training set, ours beside the paper's,
    then how the runs drew their batches and where their generated touches came from."""
    lines = ["", f"### Table {num}b: object classification from one tactile image", ""]
    lines += ["| Training set | Accuracy % ↑ (ours) | Accuracy % (paper) | seeds |", "|---|---|---|---|"]
    for r in accuracy_rows(table, data):
        n = r["ours"].n if r["ours"] else "-"
        lines.append(f"| {r['row']} | {fmt_stat(r['ours'], 'acc')} | {fmt_stat(r['paper'], 'acc')} | {n} |")
    lines += ["", "Test set: held-out ground-truth touches only; same classifier, schedule and test set per row."]
    lines.append("")
    for line in (batch_sampling(data.runs), generated_poses(data.runs)):
        if line:
            lines += [line, ""]
    return lines


def _claims_section(num: str, table: str, data: TableData) -> list[str]:
    """Markdown lines: the paper's claims checked on table ``num`` (``checks``), then our figures against the
    paper's (``against_paper``) with how far BG, the same for any generator, lies from the paper's."""
    cks = checks(table, data)
    lines = [f"### Checks against the paper's claims (Table {num})", ""]
    if cks:
        lines += ["| Claim | Verdict | Ours |", "|---|---|---|"]
        lines += [f"| {c} | {v} | {d} |" for c, v, d in cks]
    else:
        lines.append("No claim can be checked yet: the rows it compares are missing.")
    figs_vs = against_paper(table, data)
    if figs_vs:
        lines += ["", f"### Against the paper's figures (Table {num})", ""]
        lines += ["| Figure | Verdict | Ours vs paper |", "|---|---|---|"]
        lines += [f"| {c} | {v} | {d} |" for c, v, d in figs_vs]
        bg, bg_paper = data.image.get(("all", BG), {}), PAPER.get(table, {}).get("image", {}).get(("all", BG))
        if bg and bg_paper:
            lines += [
                "",
                f"BG, the same for any generator, scores SSIM {fmt_stat(bg.get('ssim'), 'ssim')} here against "
                f"the paper's {fmt_stat(bg_paper['ssim'], 'ssim')} and MSE {fmt_stat(bg.get('mse'), 'mse')} "
                f"against {fmt_stat(bg_paper['mse'], 'mse')}: how far this simulator's touches and background "
                "differ from the paper's, which the figures above inherit.",
            ]
    return lines


def write_report(
    results: Sequence[dict[str, Any]],
    folder: str | Path,
    name: str | None = None,
    notes: str | None = None,
    next_step: str | None = None,
) -> dict[str, TableData]:
    """Aggregate ``results`` (per-run dicts, see tnf.eval.aggregate) and write the report into ``folder``.

    A run's ``examples`` entry (a PNG path relative to its results file) is shown as its method's example
    figure (the lowest seed's). Returns the aggregated tables.
    """

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for r in results:
        if "_path" in r:
            p = Path(r["_path"])
            r["_rel"] = _relpath(p, folder)
    tables = aggregate(results)
    figures: dict[str, list[tuple[str, str]]] = {}
    for table, data in tables.items():
        _write_tables(folder, table, data)
        figures[table] = _table_figures(folder, table, data)
    timings = [json.loads(p.read_text()) for p in sorted((folder / "timings").glob("*.json"))]
    md = render_markdown(name or folder.name, tables, figures, notes, timings, next_step)

    if section := force_section(results, folder):  # a force-conditioned model's evaluation by force
        md += "\n" + "\n".join(section)
    write_bytes(folder / "report.md", md.encode())
    return tables


def _write_tables(folder: Path, table: str, data: TableData) -> None:
    """Write ``table``'s two CSV files into ``folder``: ``table<N>a_image.csv`` and ``table<N>b_accuracy.csv``."""
    num = TABLES.get(table, (table,))[0]
    img_rows = image_rows(table, data)
    write_bytes(
        folder / f"table{num}a_image.csv",
        csv_bytes(
            [
                "test_set",
                "method",
                "ssim_mean",
                "ssim_se",
                "mse_mean",
                "mse_se",
                "seeds",
                "paper_ssim_mean",
                "paper_ssim_se",
                "paper_mse_mean",
                "paper_mse_se",
            ],
            [
                [
                    r["test_set"],
                    r["method"],
                    *(stat_cells(r["ours"].get("ssim"))[:2]),
                    *(stat_cells(r["ours"].get("mse"))),
                    *paper_cells(r["paper"].get("ssim")),
                    *paper_cells(r["paper"].get("mse")),
                ]
                for r in img_rows
            ],
        ),
    )
    write_bytes(
        folder / f"table{num}b_accuracy.csv",
        csv_bytes(
            ["training_set", "accuracy_mean", "accuracy_se", "seeds", "paper_accuracy_mean", "paper_accuracy_se"],
            [[r["row"], *stat_cells(r["ours"]), *paper_cells(r["paper"])] for r in accuracy_rows(table, data)],
        ),
    )


def _table_figures(folder: Path, table: str, data: TableData) -> list[tuple[str, str]]:
    """Draw ``table``'s SSIM-per-object bar plots into ``folder``; returns (caption, path) of each figure, the
    methods' example figures included (a path relative to ``folder``)."""
    figs: list[tuple[str, str]] = []
    methods = [*ordered_methods(table, data), BG]
    for ts in sorted({k[0] for k in data.per_object}, key=lambda t: (t != "novel_view", t)):
        series = {m: data.per_object[(ts, m)] for m in methods if (ts, m) in data.per_object}
        if not series:
            continue
        lo = min(s.mean - s.se for v in series.values() for s in v.values())
        y_lo = max(0.0, math.floor(min(lo, 0.9) * 10) / 10)
        png = f"ssim_per_object_{table}_{ts}.png"
        bar_plot(series, f"SSIM per object, {TEST_SET_NAMES.get(ts, ts).lower()}", (y_lo, 1.0)).save(folder / png)
        figs.append((f"SSIM per object ({TEST_SET_NAMES.get(ts, ts).lower()})", png))
    for m in ordered_methods(table, data):
        # The lowest seed whose picture is there (runs gathered from several machines may lack some).
        runs = sorted((r for r in data.runs if r["method"] == m and r.get("examples")), key=lambda r: r["seed"])
        shown = [(r, Path(r["_path"]).parent / r["examples"]) for r in runs if "_path" in r]
        shown = [(r, ex) for r, ex in shown if ex.is_file()]
        if shown:
            run, ex = shown[0]
            split = str(run["examples_split"])
            caption = (
                f"{m}, {TEST_SET_NAMES.get(split, split).lower()} touches (seed {run['seed']}): RGB | "
                "depth | generated | target | thresholded difference"
            )
            figs.append((caption, _relpath(ex, folder)))
    curves = _validation_curves(folder, table, data)
    return figs + ([curves] if curves else [])


def _validation_curves(folder: Path, table: str, data: TableData) -> tuple[str, str] | None:
    """The validation SSIM of every run with a ``val_curve``, epoch by epoch, drawn into ``folder``; returns the
    (caption, file), the caption saying how long each method trained (``train.patience``'s plateau or its fixed
    epochs), or None when no run has a curve."""
    runs = sorted((r for r in data.runs if r.get("val_curve")), key=lambda r: (str(r["method"]), r["seed"]))
    if not runs:
        return None
    lines = {f"{r['method']} seed {r['seed']}": [(float(e), float(s)) for e, s in r["val_curve"]] for r in runs}
    colour_of = {f"{r['method']} seed {r['seed']}": str(r["method"]) for r in runs}
    png = f"validation_ssim_{table}.png"
    line_plot(lines, colour_of, "Validation SSIM per epoch (each run's validation split)").save(folder / png)
    notes = []
    for m in dict.fromkeys(str(r["method"]) for r in runs):
        own = [r for r in runs if r["method"] == m]
        seeds = " / ".join(str(r["seed"]) for r in own)
        epochs = " / ".join(str(len(r["val_curve"])) for r in own)
        plateau = [r["plateau"] for r in own if isinstance(r.get("plateau"), dict)]
        cut = " / ".join("yes" if r.get("unfinished") else "no" for r in own)
        if any(r.get("unfinished") for r in own):
            how = f"training cut short before it ended (cut short: {cut})"
        elif plateau:
            p = plateau[0]
            stopped = " / ".join("yes" if (r.get("plateau") or {}).get("stopped") else "no" for r in own)
            how = (
                f"until validation SSIM rose by no more than {p['min_delta']:g} for {p['patience']} validations in a "
                f"row (stopped there: {stopped})"
            )
        else:
            how = "a fixed number of epochs"
        notes.append(f"{m} (seeds {seeds}): {how}, {epochs} epochs validated")
    return "Validation SSIM per epoch, one line per run. " + "; ".join(notes), png


def _relpath(p: Path, base: Path) -> str:
    import os

    return os.path.relpath(p.absolute(), base.absolute())
