"""``tnf evaluate``: score a trained generator and write the report.

For one model (``evaluate.model=RUN``): SSIM and MSE of its generated images against ground truth on each test
split (plus the BG row, the sensor's background used as the prediction), per object too, and the classification
task (rows Sim, Sim + G, G only). The run's results go to ``<root>/reports/<name>/runs/<table>_<method>_seed<k>/``
(and to the Hydra job's output folder); then the report in ``<root>/reports/<name>/`` is rebuilt from every run
there. ``evaluate.sweep_dir=DIR`` instead collects the results.json files of a Hydra multirun folder.
"""

from __future__ import annotations

import functools
import io
import re
import shutil
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any, cast

from tnf.errors import TnfError


def run(cfg: Any) -> dict[str, Any]:
    from omegaconf import OmegaConf
    from rich.console import Console

    from tnf.artifacts import ArtifactStore, config_hash, exclusive, write_bytes, write_json
    from tnf.eval.aggregate import RESULTS_FILE, find_results, load_results
    from tnf.eval.report import write_report

    console = Console(highlight=False)
    ecfg = cfg.evaluate
    store = ArtifactStore(cfg.data_root)
    report_dir = store.path("reports", str(ecfg.name))
    runs_dir = report_dir / "runs"
    if ecfg.table not in ("main", "transfer"):
        raise TnfError(f"evaluate.table must be main or transfer, got {ecfg.table!r}")
    out: dict[str, Any] = {}
    force = bool(ecfg.force)

    if ecfg.sweep_dir:
        files = find_results(Path(str(ecfg.sweep_dir)).expanduser())
        if not files:
            raise TnfError(f"no {RESULTS_FILE} below evaluate.sweep_dir={ecfg.sweep_dir}; did the sweep's jobs finish?")
        collected = load_results(files)
        seen: dict[str, tuple[Any, str]] = {}
        for r in collected:  # the same model found twice (a sweep run again) is one run; two models are not
            rid, where = run_id(r), str(Path(r["_path"]).parent)
            if rid in seen and seen[rid][0] != r.get("model"):
                raise TnfError(
                    f"two models below {ecfg.sweep_dir} share the row {r['method']} seed {r['seed']} "
                    f"({seen[rid][1]} and {where}): give the sweep's jobs distinct row labels (evaluate.method=LABEL)"
                )
            seen[rid] = (r.get("model"), where)
            # nor does a collected run replace another model's row already in the report (checked for every run
            # before any is written, so a refused collection leaves the report as it was)
            if r.get("model") is not None:
                _check_not_another_models(runs_dir / rid / RESULTS_FILE, str(r["model"]), r["method"], r["seed"], force)
        for r in collected:
            src = Path(r.pop("_path"))
            dst = runs_dir / run_id(r)
            dst.mkdir(parents=True, exist_ok=True)
            if r.get("examples") and (src.parent / r["examples"]).is_file():
                shutil.copyfile(src.parent / r["examples"], dst / r["examples"])
            write_json(dst / RESULTS_FILE, r)
        console.print(f"collected {len(files)} run(s) from {ecfg.sweep_dir}")

    if ecfg.model:
        method = ecfg.method or _method_label(cfg)
        settings = cast(dict[str, Any], OmegaConf.to_container(cfg, resolve=True))
        # Everything that changes the numbers; not the report's name or notes, progress or the sweep folder, nor
        # where the store lives (a store that is moved or mounted elsewhere keeps its finished results).
        hashed = {k: v for k, v in settings.items() if k not in ("progress", "device", "evaluate", "data_root")}
        report_only = ("name", "notes", "next", "sweep_dir", "force")
        hashed["evaluate"] = {k: v for k, v in settings["evaluate"].items() if k not in report_only}
        chash = config_hash(hashed)
        folder = runs_dir / run_id({"table": ecfg.table, "method": method, "seed": cfg.seed})
        old = folder / RESULTS_FILE
        _check_not_another_models(old, str(ecfg.model), method, cfg.seed, force)
        if not force and old.is_file() and load_results([old])[0].get("config_hash") == chash:
            console.print(
                f"{method} seed {cfg.seed}: results exist with the same settings, skipped (evaluate.force=true)"
            )
            results = load_results([old])[0]
            results.pop("_path")
        else:
            results, examples_png, figures = evaluate_model(cfg, store, method)
            results["config_hash"] = chash
            # Again: a job beside this one (a sweep, parallel runs) may have written this row meanwhile. Nothing
            # of this run is in the row's folder until here, so a refused run leaves the other model's intact.
            _check_not_another_models(old, str(ecfg.model), method, cfg.seed, force)
            if examples_png is not None:
                write_bytes(folder / str(results["examples"]), examples_png)
            for file, png in figures.items():
                write_bytes(folder / file, png)
            write_json(folder / RESULTS_FILE, results)
        _copy_to_hydra_output(folder)
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
        notes = ecfg.get("notes")
        next_step = ecfg.get("next")
        tables = write_report(
            load_results(files),
            report_dir,
            name=str(ecfg.name),
            notes=str(notes) if notes else None,
            next_step=str(next_step) if next_step else None,
        )
    _print_summary(console, tables, report_dir)
    out["report"] = report_dir / "report.md"
    out["tables"] = tables
    return out


def run_id(r: Mapping[str, Any]) -> str:
    """Folder name of a run's results: ``<table>_<method>_seed<k>`` with unsafe characters replaced."""
    raw = f"{r.get('table', 'main')}_{r['method']}_seed{r['seed']}"
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", raw)


def _check_not_another_models(results_file: Path, model: str, method: str, seed: Any, force: bool) -> None:
    """A report holds one run per table, row label and seed: refuse to replace another model's results there
    (two models evaluated with the same label and seed, as a sweep over a generator setting would, would
    otherwise leave only the last one's numbers, silently). ``evaluate.force`` replaces them."""
    from tnf.eval.aggregate import load_results

    if force or not results_file.is_file():
        return
    other = load_results([results_file])[0].get("model")
    if other is not None and other != model:
        raise TnfError(
            f"report {results_file.parents[2].name!r} already holds {method} seed {seed} from model {other!r}; "
            f"evaluating {model!r} there would replace it. Give it its own row (evaluate.method=LABEL; in a sweep "
            "over a generator setting, a label naming that setting), its own report (evaluate.name=...), or "
            "replace it (evaluate.force=true)"
        )


def _method_label(cfg: Any) -> str:
    from tnf.eval.paper import METHOD_LABELS

    name = str(cfg.generator.name) if "generator" in cfg and "name" in cfg.generator else "G"
    return METHOD_LABELS.get(name, name)


def evaluate_model(cfg: Any, store: Any, method: str) -> tuple[dict[str, Any], bytes | None, dict[str, bytes]]:
    """Image metrics and the classification task for ``cfg.evaluate.model``: the results dict, the example
    figure as PNG bytes (None without image metrics) and further figures by file name (a force-conditioned
    model's force sweep), which the caller writes beside the results."""
    from tnf.eval.aggregate import SCHEMA
    from tnf.runtime import environment, progress, resolve_device, seed_everything

    ecfg = cfg.evaluate
    device = resolve_device(str(cfg.device))
    t0 = time.perf_counter()
    examples_png = None
    figures: dict[str, bytes] = {}
    results: dict[str, Any] = {
        "schema": SCHEMA,
        "table": str(ecfg.table),
        "method": method,
        "generator": str(cfg.generator.name) if "generator" in cfg else None,
        "model": str(ecfg.model),
        "seed": int(cfg.seed),
        "image": {},
        "accuracy": {},
        "warnings": [],
        "environment": environment(device),
    }
    with progress(bool(cfg.progress)) as bar:
        if list(ecfg.splits):
            seed_everything(int(cfg.seed))
            image, examples, force = image_metrics(cfg, store, device, bar)
            results["image"] = image
            if force is not None:  # a model conditioned on the force: its evaluation by force (tnf.eval.force)
                results["force"], figures["force_sweep.png"] = force
                results["force_figure"] = "force_sweep.png"
            if examples is not None:
                from tnf.eval.figures import example_grid

                buf = io.BytesIO()
                example_grid(examples["tensors"], float(ecfg.diff_threshold), examples["labels"]).save(buf, "PNG")
                examples_png = buf.getvalue()
                results["examples"] = "examples.png"
                results["examples_split"] = examples["split"]
        if ecfg.classify.enabled:
            seed_everything(int(cfg.seed))
            acc, info, warnings = classification(cfg, store, method, device, bar)
            results["accuracy"] = acc
            results["classify"] = info
            results["warnings"] += warnings
    results["evaluate_s"] = time.perf_counter() - t0
    return results, examples_png, figures


def image_metrics(
    cfg: Any, store: Any, device: str, bar: Any
) -> tuple[dict[str, Any], dict[str, Any] | None, tuple[dict[str, Any], bytes] | None]:
    """SSIM/MSE per test split for the model and BG, the example touches (from novel_object if scored), and for
    a model conditioned on the force its evaluation by force (``tnf.eval.force.by_force``; None otherwise)."""
    import torch
    from torch.utils.data import DataLoader

    from tnf.artifacts import MANIFEST, read_json
    from tnf.data import PairDataset, collate_pairs, sensor_mirror, training_order
    from tnf.data.datamodule import resolve_dataset
    from tnf.eval.scoring import BG, score_batches

    ecfg = cfg.evaluate
    try:
        from tnf.generators import load_generator
    except ImportError as e:
        raise TnfError(f"image metrics need tnf.generators ({e}); set evaluate.splits=[] to skip them") from None
    dataset = ecfg.dataset or (list(cfg.data.datasets)[0] if cfg.data.get("datasets") else None)
    if not dataset:
        raise TnfError("evaluate.dataset is not set: name the paired dataset (under pairs/) with the test splits")
    pairs = resolve_dataset(str(dataset), cfg.data_root)
    ckpt = store.path("models", str(ecfg.model), str(ecfg.checkpoint))
    if not ckpt.is_file():
        raise TnfError(f"checkpoint not found: {ckpt}; train it with `tnf train` or check evaluate.model/checkpoint")
    system = load_generator(ckpt, device)
    # The model makes its test images as `tnf generate` makes its images (generate.mirror_average).
    mirror = None
    if cfg.generate.mirror_average:
        mirror = sensor_mirror(read_json(pairs / MANIFEST, "dataset manifest"), pairs, required=False)
        if mirror is None:
            bar.console.print(
                f"evaluate: the sensor of dataset {pairs.name} has no mirror symmetry; test images are not "
                "mirror-averaged (generate.mirror_average)"
            )

    uses_force = system.hparams["generator"].get("force", "none") != "none"
    fixed_force = None
    if uses_force and not read_json(pairs / MANIFEST, "dataset manifest").get("force"):
        # Pairs made at one force (pair.force=false): every test touch is generated at touch.force.
        fixed_force = float(cfg.touch.force)
        bar.console.print(
            f"evaluate: dataset {pairs.name} records no forces; the model generates every touch at touch.force="
            f"{fixed_force:g} N, and the evaluation by force is skipped"
        )

    def generate(batch: Any) -> torch.Tensor:
        moved = {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in batch.items()}
        if fixed_force is not None:
            moved["force"] = torch.full((len(moved["rgb"]),), fixed_force, device=device)
        return system.generate(moved, mirror)

    out: dict[str, Any] = {}
    bg_all = None
    examples = None
    splits = list(ecfg.splits)
    example_split = "novel_object" if "novel_object" in splits else splits[-1]
    # Object ids as in training (a surface field, tnf.generators.field, knows objects by their training ids);
    # the dataset's other objects come after them.
    object_names = training_order(
        (store.manifest("models", str(ecfg.model)) or {}).get("object_names"),
        read_json(pairs / MANIFEST, "dataset manifest").get("objects") or [],
    )
    for split in splits:
        ds = PairDataset(
            pairs, splits=[split], per_object=ecfg.per_object, seed=int(cfg.seed), object_names=object_names
        )
        names = _object_names(ds)
        if len(ds) == 0:
            raise TnfError(f"split {split!r} of dataset {pairs} is empty; check evaluate.splits")
        loader = DataLoader(
            ds,
            batch_size=int(ecfg.batch_size),
            shuffle=False,
            num_workers=int(ecfg.num_workers),
            collate_fn=collate_pairs,
        )
        task = bar.add_task(f"score {split}", total=len(loader))
        keep = int(ecfg.examples) if split == example_split else 0
        accs, kept = score_batches(
            loader, generate, names, keep_examples=keep, on_batch=functools.partial(bar.advance, task)
        )
        out[split] = {"G": accs["G"].summary(), BG: accs[BG].summary()}
        bg_all = accs[BG] if bg_all is None else bg_all.merge(accs[BG])
        if keep and kept:
            labels = [names[i] if names else str(i) for i in kept["object_id"].tolist()]
            examples = {"tensors": kept, "labels": labels, "split": split}
    results: dict[str, Any] = {}
    method = cfg.evaluate.method or _method_label(cfg)
    for split, rows in out.items():
        results[split] = {method: rows["G"], BG: rows[BG]}
    if bg_all is not None:
        results["all"] = {BG: bg_all.summary()}
    force = None
    if uses_force and fixed_force is None:
        from tnf.eval.force import by_force

        force = by_force(cfg, pairs, object_names, generate, device, bar)
    return results, examples, force


def _object_names(ds: Any) -> list[str] | None:
    for attr in ("object_names", "objects"):
        names = getattr(ds, attr, None)
        if isinstance(names, (list, tuple)) and names and isinstance(names[0], str):
            return list(names)
    return None


def classification(cfg: Any, store: Any, method: str, device: str, bar: Any) -> tuple[dict, dict, list[str]]:
    """Train the classifier on Sim, Sim + G and G only; accuracy (percent) on held-out ground truth."""
    import torch
    from omegaconf import OmegaConf

    from tnf.eval.classify import ClassifierConfig, LabelledImages, load_touch_images, run_rows

    ecfg = cfg.evaluate
    ccfg = ecfg.classify
    clf = ClassifierConfig.from_dict(cast(dict[str, Any], OmegaConf.to_container(ecfg.classifier, resolve=True)))
    sensor = str(ccfg.sensor or cfg.sensor.name)
    source = str(cfg.objects.name)
    generated_run = str(ecfg.generated or ecfg.model)
    if ccfg.objects:
        objects = [str(o) for o in ccfg.objects]
    else:
        objects = [p[2] for p in store.items("touch", depth=3) if p[0] == sensor and p[1] == source]
    if cfg.object_names and not ccfg.objects:
        objects = [o for o in objects if o in set(cfg.object_names)]
    if len(objects) < 2:
        raise TnfError(
            f"classification needs touches of at least 2 objects under {store.path('touch', sensor, source)}, "
            f"found {objects}; run `tnf touch` first or set evaluate.classify.enabled=false"
        )
    size = clf.image_size
    seed = int(cfg.seed)
    sim, gen, test, warnings = [], [], [], []
    load = bar.add_task("load touches", total=len(objects))
    for label, obj in enumerate(objects):
        folder = store.require("touch", sensor, source, obj, hint="run `tnf touch` first")

        def labelled(x: torch.Tensor, label: int = label) -> LabelledImages:
            return LabelledImages(x, torch.full((len(x),), label, dtype=torch.long))

        sim.append(labelled(load_touch_images(folder, size, list(ccfg.sim_splits), ccfg.sim_per_object, seed)))
        test.append(labelled(load_touch_images(folder, size, list(ccfg.test_splits), ccfg.test_per_object, seed)))
        gfolder = store.path("generated", generated_run, source, obj)
        if (gfolder / "manifest.json").is_file():
            x = load_touch_images(gfolder, size, None, ccfg.generated_per_object, seed)
            gen.append(LabelledImages(x, torch.full((len(x),), label), torch.ones(len(x), dtype=torch.bool)))
        else:
            warnings.append(f"no generated touches for {obj} in {gfolder}")
        bar.advance(load)
    if not gen:
        raise TnfError(
            f"no generated touches of run {generated_run!r} under {store.path('generated', generated_run, source)}; "
            "run `tnf generate` first, set evaluate.generated=RUN, or evaluate.classify.enabled=false"
        )
    sim_set, gen_set, test_set = (LabelledImages.concat(s) for s in (sim, gen, test))
    rows = {"Sim": sim_set, f"Sim + {method}": LabelledImages.concat([sim_set, gen_set])}
    if ccfg.generated_only:
        rows[f"{method} only"] = gen_set
    task = bar.add_task("classify", total=clf.steps * clf.restarts * len(rows))
    acc = run_rows(rows, test_set, len(objects), clf, seed, device, on_step=lambda _: bar.advance(task))
    info = {
        "classes": objects,
        "train_images": {row: len(s) for row, s in rows.items()},
        "test_images": len(test_set),
        "sensor": sensor,
        "generated": generated_run,
        "real_fraction": clf.real_fraction,
    }
    return acc, info, warnings


def _copy_to_hydra_output(folder: Path) -> None:
    """Put the run's results into the Hydra job folder too, so a multirun folder can be aggregated later."""
    try:
        from hydra.core.hydra_config import HydraConfig

        out = Path(HydraConfig.get().runtime.output_dir)
    except (ImportError, ValueError):  # not inside a Hydra app (tests, API use)
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
