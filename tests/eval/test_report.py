"""The report renders from tiny runs: synthetic results, and `tnf evaluate` on touch folders made by code."""

import csv
import json
import shutil

import numpy as np
import pytest
import torch
from PIL import Image

from tests.eval.eval_fixtures import write_touch_folder
from tnf.eval.figures import axis_ticks, example_grid
from tnf.eval.report import write_report
from tnf.eval.scoring import score_batches
from tnf.testing import compose


def _batches(n_batches=2, b=3):
    g = torch.Generator().manual_seed(0)
    for k in range(n_batches):
        bg = torch.zeros(b, 3, 128, 128) - 0.2
        tactile = bg.clone()
        tactile[:, :, 40:80, 40:80] += torch.rand(b, 3, 1, 1, generator=g)
        yield {
            "rgb": torch.rand(b, 3, 128, 128, generator=g) * 2 - 1,
            "depth": torch.rand(b, 1, 128, 128, generator=g) * 2 - 1,
            "background": bg,
            "tactile": tactile,
            "object_id": torch.tensor([k % 2] * b),
        }


def test_scoring_perfect_generator_and_background_row():
    accs, ex = score_batches(_batches(), lambda batch: batch["tactile"], ["ball", "box"], keep_examples=4)
    g, bg = accs["G"].summary(), accs["BG"].summary()
    assert g["n"] == 6 and g["ssim"] == pytest.approx(1.0, abs=1e-4) and g["mse"] == 0
    assert set(g["per_object"]) == {"ball", "box"} and g["per_object"]["ball"]["n"] == 3
    assert bg["ssim"] < 1 and bg["mse"] > 0
    assert ex["generated"].shape == (4, 3, 128, 128) and ex["depth"].shape == (4, 1, 128, 128)
    # the examples are spread over the objects (the batches hold three ball touches, then three box touches)
    assert ex["object_id"].tolist() == [0, 1, 0, 1] and torch.equal(ex["generated"], ex["target"])
    rows = [b["tactile"][i] for b in _batches() for i in range(3)]
    assert torch.equal(ex["target"][1], rows[3]) and torch.equal(ex["target"][2], rows[1])
    _, one = score_batches(_batches(), lambda batch: batch["tactile"], ["ball", "box"], keep_examples=1)
    assert one["object_id"].tolist() == [0]
    img = example_grid(ex, threshold=20, labels=["ball"] * 4)
    assert img.size[1] > 4 * 128
    # perfect generation: the thresholded difference column is black
    arr = torch.from_numpy(np.array(img))
    last = arr[30:150, -132:-4]
    assert last.max() == 0


def _header(word, cell):
    """A grid column's header cell with ``word`` written as example_grid writes it."""
    from PIL import ImageDraw, ImageFont

    im = Image.new("RGB", (cell, 18), "white")
    ImageDraw.Draw(im).text((4, 3), word, fill="black", font=ImageFont.load_default())
    return np.array(im)


def test_example_grid_calls_the_pairs_touch_the_target_not_real():
    # The fourth column shows the pair's touch (the simulator's image, or a captured object's recorded frame).
    _, ex = score_batches(_batches(), lambda batch: batch["tactile"], ["ball", "box"], keep_examples=2)
    cell, pad = 64, 4
    img = np.array(example_grid(ex, cell=cell))
    for c, word in enumerate(["RGB", "depth", "generated", "target", "difference"]):
        x0 = pad + c * (cell + pad)
        assert np.array_equal(img[:18, x0 : x0 + cell], _header(word, cell)), word
    x0 = pad + 3 * (cell + pad)
    assert not np.array_equal(img[:18, x0 : x0 + cell], _header("real", cell))


def _result(table, method, seed, ssim, mse, acc):
    return {
        "schema": 1,
        "table": table,
        "method": method,
        "seed": seed,
        "image": {
            "novel_view": {method: {"ssim": ssim, "mse": mse, "per_object": {"ball": {"ssim": ssim, "mse": mse}}}},
            "novel_object": {
                method: {"ssim": ssim - 0.01, "mse": mse, "per_object": {"box": {"ssim": ssim, "mse": mse}}},
                "BG": {"ssim": 0.92, "mse": 67.0, "per_object": {"box": {"ssim": 0.92, "mse": 67.0}}},
            },
            "all": {"BG": {"ssim": 0.92, "mse": 67.0}},
        },
        "accuracy": {"Sim": 80.0 + seed, f"Sim + {method}": acc + seed},
    }


def test_report_tables_checks_and_figures(tmp_path):
    results = [
        _result("main", m, s, ssim, mse, acc)
        for s in range(3)
        for m, ssim, mse, acc in (("T-N", 0.97, 20.0, 95.0), ("Lee", 0.70, 1000.0, 70.0), ("Cycle", 0.6, 1600.0, 82.0))
    ] + [_result("transfer", "FS", 0, 0.8, 900.0, 81.0)]
    tables = write_report(results, tmp_path / "rep", name="tiny")
    assert set(tables) == {"main", "transfer"}
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "## Table 1" in md and "## Table 2" in md
    assert "| Novel view | T-N | 0.970 ± 0.000 | 0.980 ± 0.001 | 20.0 ± 0.0 | 14.5 ± 0.8 | 3 |" in md
    assert "| Sim + T-N | 96.0 ± 0.6 | 96.0 ± 2.0 | 3 |" in md
    # one seed has no spread to state: its value alone, beside the paper's mean ± se
    assert "| Novel view | FS | 0.800 | 0.829 ± 0.002 | 900 | 950 ± 20.0 | 1 |" in md
    assert "| Sim + FS | 81.0 | 82.0 ± 1.0 | 1 |" in md
    assert "| T-N SSIM > Lee SSIM (novel view) | holds |" in md
    assert "| Sim + T-N accuracy > Sim + Cycle | holds |" in md
    assert "| T-N SSIM > BG SSIM (novel object) | holds |" in md
    assert "| T-N MSE < BG MSE (novel object) | holds | 20.0 ± 0.0 vs 67.0 ± 0.0 |" in md
    with open(tmp_path / "rep" / "table1a_image.csv") as f:
        rows = list(csv.DictReader(f))
    lee = next(r for r in rows if r["test_set"] == "novel_view" and r["method"] == "Lee")
    assert float(lee["ssim_mean"]) == pytest.approx(0.70) and float(lee["paper_mse_mean"]) == 1040
    bg = next(r for r in rows if r["test_set"] == "all")
    assert float(bg["paper_ssim_mean"]) == 0.921 and float(bg["seeds"]) == 3
    with open(tmp_path / "rep" / "table2b_accuracy.csv") as f:
        acc = {r["training_set"]: r for r in csv.DictReader(f)}
    assert float(acc["Sim + FS"]["accuracy_mean"]) == 81.0 and float(acc["Sim + FS"]["paper_accuracy_mean"]) == 82
    assert acc["Sim + T-N"]["accuracy_mean"] == ""  # paper row without a run of ours
    png = tmp_path / "rep" / "ssim_per_object_main_novel_object.png"
    assert "ssim_per_object_main_novel_object.png" in md
    with Image.open(png) as im:
        assert im.size[0] >= 360


def test_report_says_where_each_run_ran_and_how_long_each_stage_took(tmp_path):
    """The pipeline's wall times per model (its timings files) and each run's environment end the report; runs
    evaluated before environments were recorded say so."""
    env = {"accelerator": "NVIDIA H100 80GB HBM3", "cpu_cores": 16, "python": "3.12.3", "torch": "2.11.0",
           "warp": "1.19.0", "lightning": "2.6.6", "tnf": "0.1.0", "commit": "abc1234"}  # fmt: skip
    results = [
        {**_result("main", "T-N", 0, 0.97, 20.0, 95.0), "model": "tn0", "environment": env},
        {**_result("main", "T-N", 1, 0.97, 20.0, 95.0), "model": "tn1", "environment": env, "evaluate_s": 88.5},
        {**_result("main", "Lee", 0, 0.70, 1000.0, 70.0), "model": "lee0"},
    ]
    timings = tmp_path / "rep" / "timings"
    timings.mkdir(parents=True)
    stages = {"capture": 10.0, "fit-scene": 155.0, "train": 400.25, "generate": 40.0, "evaluate": 90.0}
    (timings / "tn0.json").write_text(json.dumps({"model": "tn0", "device": "cuda", "stages": stages}))
    # written before its evaluate ran: the evaluate time comes from the run's results
    (timings / "tn1.json").write_text(json.dumps({"model": "tn1", "device": "cuda", "stages": {"train": 402.0}}))
    write_report(results, tmp_path / "rep", name="tiny")
    md = (tmp_path / "rep" / "report.md").read_text()
    where = md[md.index("## Where and how long") :]
    assert "| Model | device | capture | fit-scene | train | generate | evaluate | total |" in where
    assert "| tn0 | cuda | 10.0 | 155 | 400 | 40.0 | 90.0 | 695 |" in where
    assert "| tn1 | cuda | - | - | 402 | - | 88.5 | 490 |" in where
    env_row = "| T-N seed 0, T-N seed 1 | NVIDIA H100 80GB HBM3 | 16 | 3.12.3 | 2.11.0 | 1.19.0 | 2.6.6 "
    env_row += "| 0.1.0 (abc1234) |"
    assert env_row in where
    assert "| Lee seed 0 | not recorded |" in where
    # without timings files or environments the section is left out
    bare = [_result("main", "T-N", 0, 0.97, 20.0, 95.0)]
    write_report(bare, tmp_path / "bare", name="tiny")
    assert "## Where and how long" not in (tmp_path / "bare" / "report.md").read_text()


def test_report_compares_our_method_with_the_papers_own_figures(tmp_path):
    results = [_result("main", "Lee", s, 0.70, 1000.0, 70.0) for s in range(3)]
    # T-N: novel view 0.976 / 0.979 / 0.982 (novel object 0.01 lower), MSE 20, Sim + T-N 95-97 against Sim 80-82
    results += [_result("main", "T-N", s, ssim, 20.0, 95.0) for s, ssim in enumerate((0.976, 0.979, 0.982))]
    write_report(results, tmp_path / "rep", name="tiny")
    md = (tmp_path / "rep" / "report.md").read_text()
    part = md.split("### Against the paper's figures (Table 1)")[1].split("###")[0]
    # 0.979 ± 0.002 against the paper's 0.980 ± 0.001: short by less than the combined standard error
    assert "| T-N SSIM (novel view) | short, within noise | 0.979 ± 0.002 vs 0.980 ± 0.001 |" in part
    assert "| T-N SSIM (novel object) | reaches | 0.969 ± 0.002 vs 0.961 ± 0.000 |" in part
    assert "| T-N MSE (novel view) | FALLS SHORT | 20.0 ± 0.0 vs 14.5 ± 0.8 |" in part
    assert "| T-N MSE (novel object) | reaches | 20.0 ± 0.0 vs 84.0 ± 3.0 |" in part
    # the gain of Sim + T-N over Sim: 15 points against the paper's 96 - 85 = 11
    assert "| Sim + T-N gain over Sim (points) | reaches | 15.0 ± 0.8 vs 11.0 ± 3.6 |" in part
    assert "Lee" not in part  # the baselines' figures are the paper's to reach, not ours
    assert "BG, the same for any generator, scores SSIM 0.920 ± 0.000 here against the paper's 0.921" in part
    assert "## Notes" not in md
    lower = [{**r, "accuracy": {"Sim": 85.0, "Sim + T-N": 89.0}} for r in results]
    write_report(lower, tmp_path / "rep2", name="tiny", notes="Why the gain is smaller: the notes.\n")
    md = (tmp_path / "rep2" / "report.md").read_text()
    assert "| Sim + T-N gain over Sim (points) | FALLS SHORT | 4.0 ± 0.0 vs 11.0 ± 3.6 |" in md
    assert md.endswith("## Notes\n\nWhy the gain is smaller: the notes.\n")


def test_evaluate_summary_names_failed_claims_and_figures_below_the_papers(tmp_path):
    from rich.console import Console

    from tnf.eval.aggregate import aggregate
    from tnf.stages.evaluate import _print_summary

    # T-N below BG on novel objects (a failed claim) and below the paper's SSIM on both test sets
    results = [_result("main", "T-N", s, 0.91, 10.0, 95.0) for s in range(2)]
    console = Console(record=True, width=200)
    _print_summary(console, aggregate(results), tmp_path)
    out = console.export_text()
    assert "claims not reproduced: T-N SSIM > BG SSIM (novel object)" in out
    assert "below the paper's figures: T-N SSIM (novel view); T-N SSIM (novel object)\n" in out  # MSE 10 reaches
    # and above BG's MSE: that claim fails too
    console = Console(record=True, width=200)
    _print_summary(console, aggregate([_result("main", "T-N", s, 0.91, 90.0, 95.0) for s in range(2)]), tmp_path)
    assert "T-N SSIM > BG SSIM (novel object); T-N MSE < BG MSE (novel object)" in console.export_text()


def test_example_caption_names_the_split_it_came_from(tmp_path):
    results = []
    for seed, split in ((0, "val"), (1, "novel_object")):
        run = tmp_path / f"run{seed}"
        run.mkdir()
        Image.new("RGB", (8, 8)).save(run / "examples.png")
        r = {**_result("main", "T-N", seed, 0.97, 20.0, 95.0), "examples": "examples.png", "examples_split": split}
        r["_path"] = str(run / "results.json")
        results.append(r)
    write_report(results, tmp_path / "rep", name="tiny")
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "**T-N, validation touches (seed 0): RGB |" in md and "novel object touches" not in md
    assert "RGB | depth | generated | target | thresholded difference" in md and "| real |" not in md
    write_report(results[1:], tmp_path / "rep1", name="tiny")
    assert "**T-N, novel object touches (seed 1): RGB |" in (tmp_path / "rep1" / "report.md").read_text()
    # Runs gathered from several machines: seed 0's picture did not come along, seed 1's is shown.
    (tmp_path / "run0" / "examples.png").unlink()
    write_report(results, tmp_path / "rep2", name="tiny")
    assert "**T-N, novel object touches (seed 1): RGB |" in (tmp_path / "rep2" / "report.md").read_text()


def test_report_draws_the_validation_curves_and_says_how_long_each_method_trained(tmp_path):
    results = []
    for method, seed, plateau in (("T-N", 0, None), ("T-N", 1, None), ("Lee", 0, True), ("Lee", 1, False)):
        r = _result("main", method, seed, 0.97 if method == "T-N" else 0.7, 20.0, 95.0)
        r["val_curve"] = [[e, 0.6 + 0.01 * e] for e in range(1, 6 if plateau is None else 9)]
        if plateau is not None:
            r["plateau"] = {"patience": 3, "min_delta": 0.001, "stopped": plateau, "epochs": 8}
        results.append(r)
    write_report(results, tmp_path / "rep", name="tiny")
    md = (tmp_path / "rep" / "report.md").read_text()
    png = tmp_path / "rep" / "validation_ssim_main.png"
    assert png.is_file() and "(validation_ssim_main.png)" in md
    assert Image.open(png).size[0] > 300
    assert "T-N (seeds 0 / 1): a fixed number of epochs, 5 / 5 epochs validated" in md
    assert (
        "Lee (seeds 0 / 1): until validation SSIM rose by no more than 0.001 for 3 validations in a row "
        "(stopped there: yes / no), 8 / 8 epochs validated"
    ) in md
    # A run scored before its training ended is never passed off as a fixed schedule or a plateau.
    results.append(
        {**_result("main", "Cycle", 0, 0.7, 20.0, 95.0), "val_curve": [[1, 0.4], [2, 0.5]], "unfinished": True}
    )
    write_report(results, tmp_path / "cut", name="tiny")
    md = (tmp_path / "cut" / "report.md").read_text()
    assert "Cycle (seeds 0): training cut short before it ended (cut short: yes), 2 epochs validated" in md
    # Runs without curves (evaluated before they were recorded) draw none.
    write_report([{k: v for k, v in r.items() if k != "val_curve"} for r in results], tmp_path / "old", name="tiny")
    assert not (tmp_path / "old" / "validation_ssim_main.png").exists()


def test_axis_ticks_label_each_tick_where_it_lies():
    # An axis of 7 epochs: whole epochs only, each label its own value (a tick at 2.2 labelled "2" misread a curve).
    assert axis_ticks(1, 7, whole=True) == [(2.0, "2"), (4.0, "4"), (6.0, "6")]
    assert axis_ticks(1, 2, whole=True) == [(1.0, "1"), (2.0, "2")]
    assert [label for _, label in axis_ticks(1, 45, whole=True)] == ["10", "20", "30", "40"]
    ticks = axis_ticks(0.5, 0.75)
    assert [label for _, label in ticks] == ["0.50", "0.55", "0.60", "0.65", "0.70", "0.75"]
    assert all(abs(v - float(label)) < 1e-9 for v, label in ticks)
    assert axis_ticks(3, 3) == [(3, "3")]
    # Any span: between 1 and `most` ticks, inside it, evenly spaced.
    rng = np.random.default_rng(0)
    for _ in range(2000):
        lo = float(rng.uniform(-5, 5)) * 10.0 ** int(rng.integers(-4, 4))
        hi = lo + float(rng.uniform(1e-3, 10)) * 10.0 ** int(rng.integers(-4, 4))
        for most in (4, 6, 8):
            values = [v for v, _ in axis_ticks(lo, hi, most=most)]
            span = hi - lo
            assert 1 <= len(values) <= most and lo - 1e-9 * span <= values[0] and values[-1] <= hi + 1e-9 * span
            assert np.allclose(np.diff(values), values[1] - values[0]) if len(values) > 2 else True


def _touch_data(root, generated_run="fake", good_generator=True):
    for label, obj in enumerate(["ball", "box"]):
        write_touch_folder(root / "touch/digit/builtin" / obj, obj, label, {"train": 6, "novel_view": 4}, seed=0)
        # a generator that draws the right object's pattern, or the wrong one
        g_label = label if good_generator else 1 - label
        write_touch_folder(root / "generated" / generated_run / "builtin" / obj, obj, g_label, {"gen": 8}, seed=1)


def test_tnf_evaluate_classification_and_report(data_root, capsys):
    _touch_data(data_root)
    from tnf.stages.evaluate import run

    over = ["debug=tiny", "progress=false", "device=cpu", "evaluate.model=fake", "evaluate.splits=[]"]
    over.append("evaluate.classifier.steps=8")  # the classifier's learning is tested in test_classify
    out = run(compose("evaluate", [*over, "seed=0"]))
    acc = out["results"]["accuracy"]
    assert set(acc) == {"Sim", "Sim + T-N", "T-N only"} and all(0 <= v <= 100 for v in acc.values())
    assert out["results"]["classify"]["classes"] == ["ball", "box"]
    assert out["results"]["classify"]["train_images"] == {"Sim": 8, "Sim + T-N": 24, "T-N only": 16}
    assert out["results"]["classify"]["test_images"] == 8
    # a second seed's results, as another sweep job would write them; no model given: rebuild the report only
    r = json.loads((data_root / "reports/tiny/runs/main_T-N_seed0/results.json").read_text())
    (data_root / "reports/tiny/runs/main_T-N_seed1").mkdir()
    (data_root / "reports/tiny/runs/main_T-N_seed1/results.json").write_text(json.dumps({**r, "seed": 1}))
    out = run(compose("evaluate", ["progress=false", "evaluate.name=tiny"]))
    runs = data_root / "reports/tiny/runs"
    assert sorted(p.name for p in runs.iterdir()) == ["main_T-N_seed0", "main_T-N_seed1"]
    assert out["tables"]["main"].accuracy["Sim"].n == 2
    md = (data_root / "reports/tiny/report.md").read_text()
    assert "| Sim + T-N |" in md and "| Sim | " in md
    # a second call with the same settings (notes only end the report) reuses the results; the sweep folder mode
    # collects results files
    capsys.readouterr()
    again = run(compose("evaluate", [*over, "seed=0", "evaluate.notes='Shortfalls: see the notes.'"]))
    assert "results exist with the same settings, skipped" in capsys.readouterr().out
    assert again["results"]["accuracy"] == json.loads((runs / "main_T-N_seed0/results.json").read_text())["accuracy"]
    assert "## Notes\n\nShortfalls: see the notes.\n" in (data_root / "reports/tiny/report.md").read_text()
    out = run(compose("evaluate", ["progress=false", f"evaluate.sweep_dir={runs}", "evaluate.name=collected"]))
    assert out["tables"]["main"].accuracy["Sim + T-N"].n == 2
    assert (data_root / "reports/collected/table1b_accuracy.csv").is_file()


def test_tnf_evaluate_draws_a_share_of_each_mixed_batch_from_the_ground_truth(data_root, monkeypatch):
    import tnf.eval.classify as classify
    from tnf.stages.evaluate import run

    _touch_data(data_root)
    masks = []
    real_train = classify.train_classifiers

    def spy(sets, *args, **kwargs):
        masks.extend(s.generated.clone() for s in sets)
        return real_train(sets, *args, **kwargs)

    monkeypatch.setattr(classify, "train_classifiers", spy)
    over = ["debug=tiny", "progress=false", "device=cpu", "evaluate.model=fake", "evaluate.splits=[]", "seed=0"]
    over.append("evaluate.classifier.steps=8")
    uniform = run(compose("evaluate", [*over, "evaluate.name=uniform"]))["results"]
    half = run(compose("evaluate", [*over, "evaluate.name=half", "evaluate.classifier.real_fraction=0.5"]))["results"]
    # rows Sim, Sim + T-N, T-N only, twice: the mixed row knows its 16 generated images among 24
    assert [int(m.sum()) for m in masks] == [0, 16, 16] * 2 and [len(m) for m in masks] == [8, 24, 16] * 2
    assert (uniform["classify"]["real_fraction"], half["classify"]["real_fraction"]) == (None, 0.5)
    assert half["accuracy"]["Sim"] == uniform["accuracy"]["Sim"]  # one kind of image: drawn as before
    md = (data_root / "reports/half/report.md").read_text()
    assert "Rows that add generated images draw 50% of each batch from the ground-truth touches." in md
    md = (data_root / "reports/uniform/report.md").read_text()
    assert "draw each batch uniformly from all their images" in md


def test_the_report_says_where_the_generated_touches_came_from(data_root):
    """The generated manifests' pose source (generate.directions) reaches the results and the report."""
    from tnf.stages.evaluate import run

    _touch_data(data_root)
    cone = {"directions": "novel_view", "cone_axis": [1.0, 0.0, 0.0], "cone_deg": 30.0}
    for obj in ("ball", "box"):
        path = data_root / "generated/fake/builtin" / obj / "manifest.json"
        path.write_text(json.dumps({**json.loads(path.read_text()), "poses": cone}))
    over = ["debug=tiny", "progress=false", "device=cpu", "evaluate.model=fake", "evaluate.splits=[]", "seed=0"]
    out = run(compose("evaluate", [*over, "evaluate.classifier.steps=2"]))
    assert out["results"]["classify"]["generated_poses"] == cone
    md = (data_root / "reports/tiny/report.md").read_text()
    assert "The generated touches come from inside the held-out cone (30 degrees about [1, 0, 0]" in md
    # one object's touches from elsewhere: the runs' rows no longer say one source
    path = data_root / "generated/fake/builtin/box/manifest.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), "poses": {"directions": "sphere"}}))
    out = run(compose("evaluate", [*over, "evaluate.classifier.steps=2", "evaluate.force=true"]))
    assert out["results"]["classify"]["generated_poses"] == {"directions": "mixed"}
    md = (data_root / "reports/tiny/report.md").read_text()
    assert "held-out cone" not in md and "come from different poses" in md
    # a manifest that does not record it (made before tnf recorded poses): the report says nothing of them
    path.write_text(json.dumps({k: v for k, v in json.loads(path.read_text()).items() if k != "poses"}))
    out = run(compose("evaluate", [*over, "evaluate.classifier.steps=2", "evaluate.force=true"]))
    assert out["results"]["classify"]["generated_poses"] is None
    md = (data_root / "reports/tiny/report.md").read_text()
    assert "The generated touches come" not in md and "different poses" not in md


def test_tnf_evaluate_refuses_missing_inputs(data_root):
    from tnf.errors import TnfError
    from tnf.stages.evaluate import run

    with pytest.raises(TnfError, match="nothing to report"):
        run(compose("evaluate", ["progress=false"]))
    with pytest.raises(TnfError, match="tnf touch"):
        run(compose("evaluate", ["debug=tiny", "progress=false", "evaluate.model=x", "evaluate.splits=[]"]))


def test_tnf_evaluate_keeps_one_models_row_from_another_models_results(data_root):
    """Two models evaluated with the same row label and seed into one report (a sweep over a generator setting)
    must not leave only the last one's numbers: the second is refused unless it gets its own row or forces."""
    from tnf.errors import TnfError
    from tnf.stages.evaluate import run

    _touch_data(data_root, generated_run="first")
    _touch_data(data_root, generated_run="second")
    over = ["debug=tiny", "progress=false", "device=cpu", "evaluate.splits=[]", "evaluate.classifier.steps=4", "seed=0"]
    run(compose("evaluate", [*over, "evaluate.model=first"]))
    row = data_root / "reports/tiny/runs/main_T-N_seed0/results.json"
    with pytest.raises(TnfError, match="already holds T-N seed 0 from model 'first'"):
        run(compose("evaluate", [*over, "evaluate.model=second"]))
    assert json.loads(row.read_text())["model"] == "first"
    # its own row label: both rows in the report
    out = run(compose("evaluate", [*over, "evaluate.model=second", "evaluate.method=T-N wide"]))
    assert json.loads((data_root / "reports/tiny/runs/main_T-N_wide_seed0/results.json").read_text())["model"] == (
        "second"
    )
    assert "| Sim + T-N wide |" in (data_root / "reports/tiny/report.md").read_text()
    assert out["results"]["method"] == "T-N wide"
    # forced: the second model replaces the first's row
    run(compose("evaluate", [*over, "evaluate.model=second", "evaluate.force=true"]))
    assert json.loads(row.read_text())["model"] == "second"
    # collecting a folder where two models share a row is refused too
    sweep = data_root / "sweep"
    for job, model in enumerate(["first", "second"]):
        (sweep / str(job)).mkdir(parents=True)
        r = json.loads(row.read_text())
        (sweep / str(job) / "results.json").write_text(json.dumps({**r, "model": model}))
    with pytest.raises(TnfError, match="two models below"):
        run(compose("evaluate", ["progress=false", f"evaluate.sweep_dir={sweep}", "evaluate.name=collected"]))
    # and collecting the first model's run into the report whose row now holds the second's is refused, leaving
    # the row as it was; forced, it replaces it
    shutil.rmtree(sweep / "1")
    collect = ["progress=false", f"evaluate.sweep_dir={sweep}", "evaluate.name=tiny"]
    with pytest.raises(TnfError, match="already holds T-N seed 0 from model 'second'"):
        run(compose("evaluate", collect))
    assert json.loads(row.read_text())["model"] == "second"
    run(compose("evaluate", [*collect, "evaluate.force=true"]))
    assert json.loads(row.read_text())["model"] == "first"


def test_a_model_trained_on_its_data_made_again_replaces_its_row(data_root, capsys):
    """After an upstream change the same settings train a new run on the datasets made again: its row replaces the
    old model's, with a line that says so. A model with other settings of its own is still refused."""
    from tnf.errors import TnfError
    from tnf.generators.names import RUN_FILE
    from tnf.stages.evaluate import run

    config = {"generator": {"name": "tn_cgan", "ngf": 8}, "datasets": {"digit-hashgrid": "aaaa"}, "seed": 0}
    runs = {
        "old": config,
        "rebuilt": {**config, "datasets": {"digit-hashgrid": "bbbb"}},
        "wider": {**config, "generator": {"name": "tn_cgan", "ngf": 16}, "datasets": {"digit-hashgrid": "cccc"}},
    }
    for name, c in runs.items():
        _touch_data(data_root, generated_run=name)
        (data_root / "models" / name).mkdir(parents=True)
        (data_root / "models" / name / RUN_FILE).write_text(json.dumps({"config": c, "config_hash": name}))
    over = ["debug=tiny", "progress=false", "device=cpu", "evaluate.splits=[]", "evaluate.classifier.steps=4", "seed=0"]
    row = data_root / "reports/tiny/runs/main_T-N_seed0/results.json"
    run(compose("evaluate", [*over, "evaluate.model=old"]))
    capsys.readouterr()
    run(compose("evaluate", [*over, "evaluate.model=rebuilt"]))
    assert json.loads(row.read_text())["model"] == "rebuilt"
    assert "T-N seed 0: the results of model 'old' replaced by those of 'rebuilt'" in capsys.readouterr().out
    with pytest.raises(TnfError, match="already holds T-N seed 0 from model 'rebuilt'"):
        run(compose("evaluate", [*over, "evaluate.model=wider"]))
    assert json.loads(row.read_text())["model"] == "rebuilt"


def test_parallel_jobs_rebuild_the_report_one_at_a_time(data_root, capsys):
    """Jobs of a sweep each rebuild the report from every run present. A rebuild waits while another job holds
    the report (writing its run, then its own rebuild), so the report written last lists that job's run too."""
    import threading

    from tnf.artifacts import exclusive, write_json
    from tnf.stages.evaluate import run

    report = data_root / "reports" / "sweep"
    write_json(report / "runs" / "main_T-N_seed0" / "results.json", _result("main", "T-N", 0, 0.97, 20.0, 95.0))
    cfg = compose("evaluate", ["progress=false", "evaluate.name=sweep"])  # rebuilds the report only
    rebuilds: list = []
    with exclusive(report):  # another job, between writing its run and rebuilding
        job = threading.Thread(target=lambda: rebuilds.append(run(cfg)))
        job.start()
        job.join(timeout=3)
        assert job.is_alive() and not (report / "report.md").exists()  # waiting for the report
        write_json(report / "runs" / "main_T-N_seed1" / "results.json", _result("main", "T-N", 1, 0.97, 22.0, 95.0))
    job.join()
    # The printed tables say how many seeds each row averages.
    assert "seeds: T-N 2, BG 2" in capsys.readouterr().out
    assert (
        rebuilds
        and "| Novel view | T-N | 0.970 ± 0.000 | 0.980 ± 0.001 | 21.0 ± 1.0 |" in (report / "report.md").read_text()
    )


def test_report_opens_with_its_verdict_in_plain_words(tmp_path):
    results = [_result("main", "T-N", s, 0.97, 20.0, 95.0) for s in range(3)]
    write_report(results, tmp_path / "ok", name="tiny", next_step="Next: `tnf pipeline experiment=sim_digit`.")
    first = (tmp_path / "ok" / "report.md").read_text().split("\n\n")[1]
    assert first.startswith("**Every claim of the paper that this run checks holds (3 of 3, on 3 seeds).**")
    assert "T-N's generated touches are closer to the true ones than the background image on novel objects" in first
    assert "a better object classifier (96.0 ± 0.6 % against 81.0 ± 0.6 %)" in first
    assert "T-N's SSIM here (novel view / novel object: 0.970 / 0.960) is below the paper's (0.980 / 0.961)" in first
    assert first.endswith("Next: `tnf pipeline experiment=sim_digit`.")
    # T-N under BG in SSIM on the novel object: the verdict names the failed claim first, and no longer says
    # that T-N's images beat the background image
    write_report([_result("main", "T-N", 0, 0.91, 20.0, 95.0)], tmp_path / "bad", name="tiny")
    first = (tmp_path / "bad" / "report.md").read_text().split("\n\n")[1]
    assert first.startswith(
        "**2 of 3 claims of the paper hold on 1 seed; these do not: T-N above BG in SSIM on novel objects "
        "(0.900 against 0.920).**"
    )
    assert "closer to the true ones" not in first


def test_a_claim_that_fails_by_less_than_the_spread_between_seeds_says_so(tmp_path):
    # novel-object SSIM 0.91 ± 0.012 over three seeds against BG's 0.92: below it, within the spread
    results = [_result("main", "T-N", s, v, 20.0, 95.0) for s, v in enumerate((0.92, 0.94, 0.90))]
    write_report(results, tmp_path / "rep", name="tiny")
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "| T-N SSIM > BG SSIM (novel object) | FAILS (within noise) |" in md
    assert "on novel objects (0.910 ± 0.012 against 0.920 ± 0.000, within the spread between seeds)" in md
    # one seed has no spread: a failure is a plain failure
    write_report(results[:1], tmp_path / "one", name="tiny")
    assert (
        "| T-N SSIM > BG SSIM (novel object) | FAILS | 0.910 vs 0.920 |" in (tmp_path / "one" / "report.md").read_text()
    )
