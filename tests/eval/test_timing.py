"""The phases of `tnf evaluate`: their seconds in each run's results, the loader's and the scoring's cuts."""

import json

import numpy as np
import torch
from PIL import Image

from tests.eval.eval_fixtures import tactile_image, write_touch_folder
from tnf.eval.classify import load_touch_images, subset, touch_count
from tnf.eval.scoring import score_batches
from tnf.eval.timing import Phases, phases_line
from tnf.testing import compose
from tnf.testing.references import load_touch_images_one_by_one


def test_phases_accumulate_in_the_order_they_first_ran():
    t = Phases("cpu")
    with t.phase("a"):
        pass
    with t.phase("b"):
        pass
    t.add("a", 1.0)
    assert list(t.seconds) == ["a", "b"] and t.seconds["a"] >= 1.0
    assert set(t.record()) == {"a", "b"} and all(isinstance(v, float) for v in t.record().values())
    line = phases_line({"a": 1.25, "b": 2.0})
    assert line == "evaluate phases (s): a 1.2, b 2.0 | sum 3.2"


def _batches(n_batches=3, b=4):
    g = torch.Generator().manual_seed(0)
    for k in range(n_batches):
        bg = torch.zeros(b, 3, 128, 128) - 0.2
        yield {
            "rgb": torch.rand(b, 3, 128, 128, generator=g) * 2 - 1,
            "depth": torch.rand(b, 1, 128, 128, generator=g) * 2 - 1,
            "background": bg,
            "tactile": (bg + torch.rand(b, 3, 128, 128, generator=g) * 0.3).clamp(-1, 1),
            "object_id": torch.tensor([k % 2] * b),
        }


def test_scoring_records_its_phases_and_scores_as_without_them():
    def gen(batch):
        return (batch["tactile"] * 0.9).clamp(-1, 1)

    t = Phases("cpu")
    with_t, ex_t = score_batches(_batches(), gen, ["ball", "box"], keep_examples=2, phases=t, prefix="nv.")
    alone, ex = score_batches(_batches(), gen, ["ball", "box"], keep_examples=2)
    assert set(t.seconds) == {"nv.data", "nv.generate", "nv.metrics"}
    for row in ("G", "BG"):
        assert with_t[row].summary() == alone[row].summary()
    assert all(torch.equal(ex_t[k], ex[k]) for k in ex)
    # the background row alone (no generator): no generate phase is needed, yet it is scored
    t = Phases()
    accs, kept = score_batches(_batches(), None, ["ball", "box"], phases=t)
    assert accs["BG"].summary()["n"] == 12 and accs["G"].summary()["n"] == 0 and kept == {}


def test_loader_reads_each_image_as_the_per_image_loop_did(tmp_path, monkeypatch):
    import tnf.eval.classify as classify

    folder = write_touch_folder(tmp_path / "ball", "ball", 0, {"train": 7, "novel_view": 3})
    # images of another shape among them: each shape is resized on its own
    Image.fromarray(tactile_image(1, np.random.default_rng(5), 160, 120)).save(folder / "images" / "00002.png")
    monkeypatch.setattr(classify, "_RESIZE_CHUNK", 3)  # chunks that split a shape's images
    for size in (32, 64, 128):
        ref = load_touch_images_one_by_one(folder, size)
        assert torch.equal(load_touch_images(folder, size), ref)
        assert torch.equal(load_touch_images(folder, size, workers=1), ref)
        assert torch.equal(load_touch_images(folder, size, workers=3), ref)
    fast = load_touch_images(folder, 32, ["train"], limit=4, seed=3)
    assert torch.equal(fast, load_touch_images_one_by_one(folder, 32, ["train"], 4, 3))
    # rows: only those touches are read, as the full load holds them
    assert touch_count(folder, ["train"]) == 7 and touch_count(folder) == 10
    rows = np.array([1, 2, 5])
    full = load_touch_images(folder, 32, ["train"])
    assert torch.equal(load_touch_images(folder, 32, ["train"], rows=rows), full[torch.from_numpy(rows)])


def _touch_data(root):
    for label, obj in enumerate(["ball", "box"]):
        write_touch_folder(root / "touch/digit/builtin" / obj, obj, label, {"train": 9, "novel_view": 4}, seed=0)
        write_touch_folder(root / "generated/fake/builtin" / obj, obj, label, {"gen": 5}, seed=1)


def test_evaluate_reads_only_the_sim_touches_its_restarts_draw_and_records_its_phases(data_root, monkeypatch, capsys):
    import tnf.eval.classify as classify
    from tnf.eval.classify import restart_seed
    from tnf.stages.evaluate import run

    _touch_data(data_root)
    sets, reads = [], []
    real_train, real_load = classify.train_classifiers, classify.load_touch_images

    def spy_train(s, *args, **kwargs):
        sets.extend(s)
        return real_train(s, *args, **kwargs)

    def spy_load(folder, *args, **kwargs):
        x = real_load(folder, *args, **kwargs)
        reads.append((str(folder), kwargs.get("rows") is not None, len(x)))
        return x

    monkeypatch.setattr(classify, "train_classifiers", spy_train)
    monkeypatch.setattr(classify, "load_touch_images", spy_load)
    over = ["debug=tiny", "progress=false", "device=cpu", "evaluate.model=fake", "evaluate.splits=[]", "seed=0"]
    over += ["evaluate.classifier.steps=4", "evaluate.classifier.restarts=2", "evaluate.classify.sim_per_object=3"]
    out = run(compose("evaluate", over))
    # Sim rows: each restart's draw of 3 of the 9 train touches per object, the images a full load gives them
    sims = [s for s in sets if len(s) == 6 and not bool(s.generated.any())]
    assert len(sims) == 2
    for k, sim in enumerate(sims):
        seed = restart_seed(0, k)
        want = []
        for obj in ("ball", "box"):
            full = real_load(data_root / "touch/digit/builtin" / obj, 32, ["train"])
            want.append(full[torch.from_numpy(subset(9, 3, seed))])
        assert torch.equal(sim.images, torch.cat(want))
    # of each object's 9 train touches, only those drawn were read (at most the 2 x 3 drawn)
    sim_reads = [n for f, rows, n in reads if rows]
    assert len(sim_reads) == 2 and all(3 <= n <= 6 for n in sim_reads)
    # the phases, in the results (the file too) and on one line at the end
    phases = out["results"]["phases_s"]
    assert {"setup", "classify.load", "classify.train", "classify.predict", "write", "report"} <= set(phases)
    assert all(v >= 0 for v in phases.values())
    saved = json.loads((data_root / "reports/tiny/runs/main_T-N_seed0/results.json").read_text())
    assert saved["phases_s"] == phases
    printed = capsys.readouterr().out.splitlines()
    assert any(line.startswith("evaluate phases (s): setup ") for line in printed)
