"""Score one trained generator (``tnf evaluate``): image metrics on the test splits and the classification task.

``evaluate_model`` returns the run's results (the ``results.json`` of ``tnf.eval.aggregate``) with its figures;
``collect_sweep`` gathers the results of a Hydra multirun folder into a report's ``runs/``.
"""

from __future__ import annotations

import functools
import io
import json
import logging
import re
import shutil
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tnf.artifacts import MANIFEST, read_json, write_json
from tnf.errors import TnfError
from tnf.eval.aggregate import RESULTS_FILE, SCHEMA, find_results, load_results
from tnf.eval.settings import EvaluateSettings
from tnf.eval.timing import Phases
from tnf.runtime import environment, progress, resolve_device, seed_everything

log = logging.getLogger(__name__)


@dataclass
class EvalJob:
    """What ``tnf evaluate`` scores, built from the run's config by the stage.

    ``settings`` is the ``evaluate`` section; ``method`` the row label; ``generator`` the generator group's
    name (None without one); ``datasets`` the ``data.datasets`` list (the default test dataset); ``objects`` and
    ``simulator`` those groups' config nodes as plain dicts; ``object_names`` the run's selected objects.
    """

    settings: EvaluateSettings
    method: str
    seed: int
    device: str
    progress: bool
    data_root: str
    generator: str | None
    datasets: list[str] | None
    mirror_average: bool
    touch_force: float
    sensor: str
    objects: dict[str, Any]
    object_names: list[str] | None
    simulator: dict[str, Any]


def run_id(r: Mapping[str, Any]) -> str:
    """Folder name of a run's results: ``<table>_<method>_seed<k>`` with unsafe characters replaced."""
    raw = f"{r.get('table', 'main')}_{r['method']}_seed{r['seed']}"
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", raw)


def check_not_another_models(
    results_file: Path, model: str, method: str, seed: Any, force: bool, models: Path | None = None
) -> str | None:
    """A report holds one run per table, row label and seed: refuse to replace another model's results there
    (two models evaluated with the same label and seed, as a sweep over a generator setting would, would
    otherwise leave only the last one's numbers, silently). ``evaluate.force`` replaces them. So does a model
    whose settings (``models/<run>/run.json``, ``models``: the store's model folder) differ from the other's in
    the content of their datasets only (the data made again after an upstream change): then the line returned
    says so. None when nothing is replaced."""

    if force or not results_file.is_file():
        return None
    other = load_results([results_file])[0].get("model")
    if other is not None and other != model and models is not None and _data_rebuilt(models, str(other), model):
        return (
            f"{method} seed {seed}: the results of model {other!r} replaced by those of {model!r}, the same settings "
            "trained on its datasets made again"
        )
    if other is not None and other != model:
        raise TnfError(
            f"report {results_file.parents[2].name!r} already holds {method} seed {seed} from model {other!r}; "
            f"evaluating {model!r} there would replace it. Give it its own row (evaluate.method=LABEL; in a sweep "
            "over a generator setting, a label naming that setting), its own report (evaluate.name=...), or "
            "replace it (evaluate.force=true)"
        )
    return None


def _data_rebuilt(models: Path, old: str, new: str) -> bool:
    """Whether model runs ``old`` and ``new`` under ``models`` have the same settings but for their datasets'
    content (the ``datasets`` hashes of their ``run.json``); False when either record is missing or unreadable."""
    from tnf.generators.names import RUN_FILE

    configs = []
    for run in (old, new):
        try:
            configs.append(json.loads((models / run / RUN_FILE).read_text())["config"])
        except (OSError, ValueError, TypeError, KeyError):
            return False
    a, b = configs
    if not isinstance(a, dict) or not isinstance(b, dict) or set(a) != set(b) or "datasets" not in a:
        return False
    same_names = (
        isinstance(a["datasets"], dict) and isinstance(b["datasets"], dict) and set(a["datasets"]) == set(b["datasets"])
    )
    return same_names and all(a[k] == b[k] for k in a if k != "datasets")


def collect_sweep(sweep_dir: str, runs_dir: Path, force: bool) -> int:
    """Copy the results of a Hydra multirun folder into a report's ``runs/``; returns how many were found."""

    files = find_results(Path(sweep_dir).expanduser())
    if not files:
        raise TnfError(f"no {RESULTS_FILE} below evaluate.sweep_dir={sweep_dir}; did the sweep's jobs finish?")
    collected = load_results(files)
    seen: dict[str, tuple[Any, str]] = {}
    for r in collected:  # the same model found twice (a sweep run again) is one run; two models are not
        rid, where = run_id(r), str(Path(r["_path"]).parent)
        if rid in seen and seen[rid][0] != r.get("model"):
            raise TnfError(
                f"two models below {sweep_dir} share the row {r['method']} seed {r['seed']} "
                f"({seen[rid][1]} and {where}): give the sweep's jobs distinct row labels (evaluate.method=LABEL)"
            )
        seen[rid] = (r.get("model"), where)
        # nor does a collected run replace another model's row already in the report (checked for every run
        # before any is written, so a refused collection leaves the report as it was)
        if r.get("model") is not None:
            check_not_another_models(runs_dir / rid / RESULTS_FILE, str(r["model"]), r["method"], r["seed"], force)
    for r in collected:
        src = Path(r.pop("_path"))
        dst = runs_dir / run_id(r)
        dst.mkdir(parents=True, exist_ok=True)
        if r.get("examples") and (src.parent / r["examples"]).is_file():
            shutil.copyfile(src.parent / r["examples"], dst / r["examples"])
        write_json(dst / RESULTS_FILE, r)
    return len(files)


def evaluate_model(
    job: EvalJob, store: Any, phases: Phases | None = None
) -> tuple[dict[str, Any], bytes | None, dict[str, bytes]]:
    """Image metrics and the classification task for ``evaluate.model``: the results dict, the example
    figure as PNG bytes (None without image metrics) and further figures by file name (a force-conditioned
    model's force sweep), which the caller writes beside the results.

    ``phases`` (``tnf.eval.timing.Phases``; a fresh one if None) gets the wall seconds of each phase: ``setup``,
    ``load_model``, per test split ``<split>.data`` (reading and batching its pairs), ``<split>.generate`` (the
    model's images), ``<split>.metrics`` (SSIM, MSE and the example touches), ``by_force``, ``examples_figure``,
    ``classify.load`` (reading the touches), ``classify.train``, ``classify.predict``; ``results["phases_s"]``
    holds them as they stand at return."""

    ecfg = job.settings
    device = resolve_device(job.device)
    timer = phases if phases is not None else Phases(device)
    t0 = time.perf_counter()
    examples_png = None
    figures: dict[str, bytes] = {}
    results: dict[str, Any] = {
        "schema": SCHEMA,
        "table": ecfg.table,
        "method": job.method,
        "generator": job.generator,
        "model": str(ecfg.model),
        "seed": job.seed,
        "image": {},
        "accuracy": {},
        "warnings": [],
    }
    with timer.phase("setup"):
        results["environment"] = environment(device)
        results.update(
            training_record(store.path("models", str(ecfg.model)), store.manifest("models", str(ecfg.model)))
        )
        if results.get("unfinished"):
            msg = f"model {ecfg.model} has not finished training: scored from its {ecfg.checkpoint} as it is"
            log.warning(msg)
            results["warnings"].append(msg)
    with progress(job.progress) as bar:
        if ecfg.splits:
            seed_everything(job.seed)
            image, examples, force = image_metrics(job, store, device, bar, timer)
            results["image"] = image
            if force is not None:  # a model conditioned on the force: its evaluation by force (tnf.eval.force)
                results["force"], figures["force_sweep.png"] = force
                results["force_figure"] = "force_sweep.png"
            if examples is not None:
                from tnf.eval.figures import example_grid

                with timer.phase("examples_figure"):
                    buf = io.BytesIO()
                    example_grid(examples["tensors"], ecfg.diff_threshold, examples["labels"]).save(buf, "PNG")
                    examples_png = buf.getvalue()
                results["examples"] = "examples.png"
                results["examples_split"] = examples["split"]
        if ecfg.classify.enabled:
            seed_everything(job.seed)
            acc, info, warnings = classification(job, store, device, bar, timer)
            results["accuracy"] = acc
            results["classify"] = info
            results["warnings"] += warnings
    results["evaluate_s"] = time.perf_counter() - t0
    results["phases_s"] = timer.record()
    return results, examples_png, figures


def training_record(run_dir: Path, manifest: dict[str, Any] | None) -> dict[str, Any]:
    """What the report shows of a model's training: ``val_curve`` ([[epoch, validation SSIM], ...] from its
    ``metrics.csv``, epochs counted from 1), ``plateau`` (``train.patience``'s record in its manifest), each
    only where the run has it, and ``unfinished: True`` for a run folder without a manifest (its training was cut
    short; it is scored from its checkpoint as it is). Rows that do not parse are left out of the curve, with a
    warning: the curve is an aside, the evaluation goes on."""
    out: dict[str, Any] = {}
    metrics = run_dir / "metrics.csv"
    if metrics.is_file():
        import csv

        curve: dict[int, float] = {}
        bad = 0
        with metrics.open(newline="", encoding="utf-8") as f:
            for row in csv.DictReader(f):
                if not (row.get("val_ssim") and row.get("epoch")):
                    continue
                try:
                    curve[int(row["epoch"]) + 1] = float(row["val_ssim"])
                except ValueError:
                    bad += 1
        if bad:
            log.warning("%s: %d rows of val_ssim that are not numbers, left out of the validation curve", metrics, bad)
        if curve:
            out["val_curve"] = [[e, curve[e]] for e in sorted(curve)]
    if manifest and isinstance(manifest.get("plateau"), dict):
        out["plateau"] = {**manifest["plateau"], "epochs": manifest.get("epochs")}
    if manifest is None and run_dir.is_dir():
        out["unfinished"] = True
    return out


def image_metrics(
    job: EvalJob, store: Any, device: str, bar: Any, phases: Phases | None = None
) -> tuple[dict[str, Any], dict[str, Any] | None, tuple[dict[str, Any], bytes] | None]:
    """SSIM/MSE per test split for the model and BG, the example touches (from novel_object if scored), and for
    a model conditioned on the force its evaluation by force (``tnf.eval.force.by_force``; None otherwise)."""
    from torch.utils.data import DataLoader

    # Lazy: torch-heavy; tnf evaluate imports this module before Hydra composes.
    from tnf.data import PairDataset, collate_pairs, training_order
    from tnf.data.datamodule import resolve_dataset
    from tnf.eval.scoring import BG, score_batches

    timer = phases if phases is not None else Phases(device)
    ecfg = job.settings
    dataset = ecfg.dataset or (job.datasets[0] if job.datasets else None)
    if not dataset:
        raise TnfError("evaluate.dataset is not set: name the paired dataset (under pairs/) with the test splits")
    pairs = resolve_dataset(str(dataset), job.data_root)
    from tnf.generators.names import require_checkpoint

    ckpt = require_checkpoint(store.path("models", str(ecfg.model), ecfg.checkpoint), "evaluate.model")
    with timer.phase("load_model"):
        generate, uses_force, fixed_force = _model_images(job, ckpt, pairs, device, bar)
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
        with timer.phase(f"{split}.data"):
            ds = PairDataset(
                pairs, splits=[split], per_object=ecfg.per_object, seed=job.seed, object_names=object_names
            )
        names = _object_names(ds)
        if len(ds) == 0:
            raise TnfError(f"split {split!r} of dataset {pairs} is empty; check evaluate.splits")
        loader = DataLoader(
            ds,
            batch_size=ecfg.batch_size,
            shuffle=False,
            num_workers=ecfg.num_workers,
            collate_fn=collate_pairs,
        )
        task = bar.add_task(f"score {split}", total=len(loader))
        keep = ecfg.examples if split == example_split else 0
        accs, kept = score_batches(
            loader,
            generate,
            names,
            keep_examples=keep,
            on_batch=functools.partial(bar.advance, task),
            phases=timer,
            prefix=f"{split}.",
        )
        out[split] = {"G": accs["G"].summary(), BG: accs[BG].summary()}
        bg_all = accs[BG] if bg_all is None else bg_all.merge(accs[BG])
        if keep and kept:
            labels = [names[i] if names else str(i) for i in kept["object_id"].tolist()]
            examples = {"tensors": kept, "labels": labels, "split": split}
    results: dict[str, Any] = {}
    for split, rows in out.items():
        results[split] = {job.method: rows["G"], BG: rows[BG]}
    if bg_all is not None:
        results["all"] = {BG: bg_all.summary()}
    force = None
    recorded = read_json(pairs / MANIFEST, "dataset manifest").get("force") or {}
    if uses_force and fixed_force is None and not recorded.get("range"):
        # Pairs of touches pressed at one force (touch.force_range=null): no bands to evaluate by
        bar.console.print(
            f"evaluate: the touches of dataset {pairs.name} were pressed at one force (touch.force_range=null); "
            "the evaluation by force is skipped"
        )
    elif uses_force and fixed_force is None:
        from tnf.eval.force import by_force

        with timer.phase("by_force"):
            force = by_force(
                ecfg, job.seed, pairs, object_names, generate, device, bar,
                data_root=job.data_root, objects=job.objects, simulator=job.simulator,
            )  # fmt: skip
    return results, examples, force


def _model_images(job: EvalJob, ckpt: Path, pairs: Path, device: str, bar: Any) -> tuple[Any, bool, float | None]:
    """The model's images of a batch (made as `tnf generate` makes them), whether it is conditioned on the force,
    and the one force it is given when the dataset records none (else None)."""
    import torch

    from tnf.data import sensor_mirror

    try:
        from tnf.generators import load_generator
    except ImportError as e:
        raise TnfError(f"image metrics need tnf.generators ({e}); set evaluate.splits=[] to skip them") from None

    system = load_generator(ckpt, device)
    # The model makes its test images as `tnf generate` makes its images (generate.mirror_average).
    mirror = None
    if job.mirror_average:
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
        fixed_force = job.touch_force
        bar.console.print(
            f"evaluate: dataset {pairs.name} records no forces; the model generates every touch at touch.force="
            f"{fixed_force:g} N, and the evaluation by force is skipped"
        )

    def generate(batch: Any) -> torch.Tensor:
        moved = {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in batch.items()}
        if fixed_force is not None:
            moved["force"] = torch.full((len(moved["rgb"]),), fixed_force, device=device)
        return system.generate(moved, mirror)

    return generate, uses_force, fixed_force


def _object_names(ds: Any) -> list[str] | None:
    for attr in ("object_names", "objects"):
        names = getattr(ds, attr, None)
        if isinstance(names, (list, tuple)) and names and isinstance(names[0], str):
            return list(names)
    return None


def classification(
    job: EvalJob, store: Any, device: str, bar: Any, phases: Phases | None = None
) -> tuple[dict, dict, list[str]]:
    """Train the classifier on Sim, Sim + G and G only; accuracy (percent) on held-out ground truth."""
    import numpy as np
    import torch

    from tnf.eval.classify import LabelledImages, load_touch_images, restart_seed, run_rows, subset, touch_count

    timer = phases if phases is not None else Phases(device)
    ecfg, method = job.settings, job.method
    ccfg = ecfg.classify
    clf = ecfg.classifier
    sensor = ccfg.sensor or job.sensor
    source = str(job.objects["name"])
    generated_run = str(ecfg.generated or ecfg.model)
    if ccfg.objects:
        objects = list(ccfg.objects)
    else:
        objects = store.items("touch", sensor, source)
    if job.object_names and not ccfg.objects:
        objects = [o for o in objects if o in set(job.object_names)]
    if len(objects) < 2:
        raise TnfError(
            f"classification needs touches of at least 2 objects under {store.path('touch', sensor, source)}, "
            f"found {objects}; run `tnf touch` first or set evaluate.classify.enabled=false"
        )
    size = clf.image_size
    seed = job.seed
    limit = ccfg.sim_per_object
    seeds = [restart_seed(seed, k) for k in range(clf.restarts)]  # the seeds run_rows gives `rows` below
    sim: list[tuple[int, np.ndarray, LabelledImages]] = []  # per object: its Sim touches, those read, their images
    gen, test, warnings = [], [], []
    poses: list[Any] = []  # each generated object's pose source (its manifest's "poses")
    load = bar.add_task("load touches", total=len(objects))
    with timer.phase("classify.load"):
        for label, obj in enumerate(objects):
            folder = store.require("touch", sensor, source, obj, hint="run `tnf touch` first")

            def labelled(x: torch.Tensor, label: int = label) -> LabelledImages:
                return LabelledImages(x, torch.full((len(x),), label, dtype=torch.long))

            # Each restart draws its own sim_per_object of the Sim splits' touches: only the touches some draw
            # takes are read (all of them where the draws take every touch).
            n = touch_count(folder, list(ccfg.sim_splits))
            read = np.unique(np.concatenate([subset(n, limit, s) for s in seeds])) if n else np.arange(0)
            sim.append((n, read, labelled(load_touch_images(folder, size, list(ccfg.sim_splits), rows=read))))
            tests = load_touch_images(folder, size, list(ccfg.test_splits), ccfg.test_per_object, seed)
            test.append(labelled(tests))
            gfolder = store.path("generated", generated_run, source, obj)
            if (gfolder / "manifest.json").is_file():
                poses.append(read_json(gfolder / "manifest.json", "generated manifest").get("poses"))
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
    gen_set, test_set = LabelledImages.concat(gen), LabelledImages.concat(test)

    def rows(restart_seed: int) -> dict[str, LabelledImages]:
        # The Sim set of one restart: its own draw of sim_per_object touches per object, shared by its rows, so
        # that a row's accuracy averages over draws of the few ground-truth touches as well as over classifiers.
        drawn = []
        for n, read, s in sim:
            want = subset(n, limit, restart_seed)
            at = np.searchsorted(read, want)
            if not np.array_equal(read[np.minimum(at, len(read) - 1)], want):
                raise AssertionError(f"restart seed {restart_seed} draws Sim touches that were not read")
            idx = torch.from_numpy(at)
            drawn.append(LabelledImages(s.images[idx], s.labels[idx]))
        sim_set = LabelledImages.concat(drawn)
        out = {"Sim": sim_set, f"Sim + {method}": LabelledImages.concat([sim_set, gen_set])}
        if ccfg.generated_only:
            out[f"{method} only"] = gen_set
        return out

    first = rows(seed)
    task = bar.add_task("classify", total=clf.steps * clf.restarts * len(first))
    acc = run_rows(rows, test_set, len(objects), clf, seed, device, on_step=lambda _: bar.advance(task), phases=timer)
    info = {
        "classes": objects,
        "train_images": {row: len(s) for row, s in first.items()},
        "test_images": len(test_set),
        "sensor": sensor,
        "generated": generated_run,
        "real_fraction": clf.real_fraction,
        "generated_poses": _one_pose_source(poses),
    }
    return acc, info, warnings


def _one_pose_source(poses: list[Any]) -> dict[str, Any] | None:
    """The generated objects' pose source (their manifests' ``poses``): the one they share, ``{"directions":
    "mixed"}`` where they differ, None where some object's manifest does not record it."""
    if not poses or None in poses:
        return None
    return poses[0] if all(p == poses[0] for p in poses) else {"directions": "mixed"}
