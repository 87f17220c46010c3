"""The force chain at tiny scale: touches at many forces -> pairs with their force -> a force-conditioned generator
(FiLM and input plane) -> generation at requested forces -> evaluation by force. Real meshes, simulator and
training steps; the scene the generator renders from is an exact sphere."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from tnf.cli import main
from tnf.data import PairDataset, open_pairs
from tnf.errors import TnfError
from tnf.testing import compose

MESH = ["debug=tiny", "progress=false", "device=cpu", "sensor.noise_std=0", "pair.scene_source=mesh"]
FORCE = ["touch.force_range={min:1.0,max:8.0}", "touch.n_novel_view=6", "pair.force=true"]


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    root = tmp_path_factory.mktemp("force") / "tnf-data"
    for stage in ("capture", "touch", "pair"):
        assert main([stage, f"data_root={root}", *MESH, *FORCE]) == 0
    return root


def _base(root):
    return [f"data_root={root}", *MESH, *FORCE, "data.batch_size=4", "data.datasets=[digit-mesh]"]


@pytest.fixture(scope="module")
def models(store):
    from tnf.stages import train

    for mode in ("film", "plane"):
        over = ["generator=tn_cgan_force", f"generator.force={mode}", f"train.run_name={mode}", "train.epochs=2"]
        train.run(compose("train", [*_base(store), *over]))
    train.run(compose("train", [*_base(store), "generator=tn_cgan", "train.run_name=fixed", "train.epochs=1"]))
    return store


def test_pairs_carry_each_touchs_force(store):
    a = open_pairs(store / "pairs" / "digit-mesh")
    assert a.force is not None and a.force.dtype == np.float32 and a.manifest["force"]["range"]["max"] == 8.0
    for oid, name in enumerate(a.objects):
        m = json.loads((store / "touch" / "digit" / "builtin" / name / "manifest.json").read_text())
        rows = np.flatnonzero(a.object_id == oid)
        want = [m["touches"][i]["force"] for i in a.touch_index[rows]]
        assert np.allclose(a.force[rows], want)
    b = PairDataset(store / "pairs" / "digit-mesh", splits=("novel_view",)).__getitems__([0, 1])
    assert b["force"].dtype == torch.float32 and b["force"].shape == (2,)


def test_both_force_inputs_train_and_their_images_follow_the_force(models):
    from tnf.generators import load_generator

    ds = PairDataset(models / "pairs" / "digit-mesh", splits=("novel_view",))
    batch = ds.__getitems__([0, 1])
    for mode in ("film", "plane"):
        run = models / "models" / mode
        rows = (run / "metrics.csv").read_text().splitlines()
        assert len(rows) > 1 and "nan" not in rows[-1]
        system = load_generator(run / "best.ckpt")
        light = system.generate({**batch, "force": torch.full((2,), 1.0)})
        hard = system.generate({**batch, "force": torch.full((2,), 9.0)})
        # The force reaches the image. FiLM starts as the identity (the same image at every force) and after the
        # fixture's four steps has learned a little; the plane acts from the first step.
        assert (light - hard).abs().mean() > (1e-4 if mode == "plane" else 1e-7), mode
        with pytest.raises(TnfError, match="pair.force=true"):
            system.generate({k: v for k, v in batch.items() if k != "force"})


def test_film_starts_as_the_identity():
    from tnf.registry import GENERATORS

    g = GENERATORS.build({"name": "tn_cgan", "ngf": 8, "ndf": 8, "force": "film"}).eval()
    torch.manual_seed(0)
    b = {k: torch.rand(2, c, 128, 128) * 2 - 1 for k, c in (("rgb", 3), ("depth", 1), ("background", 3))}
    with torch.no_grad():
        assert torch.equal(
            g.generate({**b, "force": torch.tensor([1.0, 1.0])}), g.generate({**b, "force": torch.tensor([9.0, 9.0])})
        )
        g.net_g.film.net[-1].weight.normal_(0, 0.1)  # once trained, the force changes the image
        assert not torch.allclose(
            g.generate({**b, "force": torch.tensor([1.0, 1.0])}), g.generate({**b, "force": torch.tensor([9.0, 9.0])})
        )


def _sphere_scene(root):
    from tests.data.pair_inputs import SphereScene
    from tnf.scenes import save_scene

    save_scene(SphereScene(SphereScene.Config(radius=0.04)), root / "scenes" / "hashgrid" / "builtin" / "ball")


def test_generate_sweeps_forces_and_records_them(models, capsys):
    from tnf.stages import generate

    _sphere_scene(models)
    gen = [*_base(models), "object=ball", "generate.model=plane", "generate.n_poses=2", "generate.radius=0.1"]
    out = generate.run(compose("generate", [*gen, "generate.touch_force=[1.0,4.5,9.0]", "generate.run_name=sweep"]))
    assert out["written"] == {"ball": 6}
    # 9 N lies above the 1-8 N the model trained on: a warning names it and only it.
    warned = [line for line in capsys.readouterr().out.splitlines() if "warning" in line]
    assert len(warned) == 1 and "touch_force: 9 N lie outside" in warned[0] and "(1-8 N)" in warned[0]
    m = json.loads((models / "generated" / "sweep" / "builtin" / "ball" / "manifest.json").read_text())
    assert [(t["pose_index"], t["force"]) for t in m["touches"]] == [(p, f) for p in (0, 1) for f in (1.0, 4.5, 9.0)]
    assert m["force"]["requested"] == [1.0, 4.5, 9.0]
    # sim: the object's simulated touches, each at its own force.
    generate.run(compose("generate", [*gen, "generate.touch_force=sim", "generate.run_name=own"]))
    own = json.loads((models / "generated" / "own" / "builtin" / "ball" / "manifest.json").read_text())["touches"]
    sim = json.loads((models / "touch" / "digit" / "builtin" / "ball" / "manifest.json").read_text())["touches"]
    assert [t["force"] for t in own] == [pytest.approx(t["force"], rel=1e-5) for t in sim]
    assert [t["split"] for t in own] == [t["split"] for t in sim]
    # A model trained without force refuses a requested force in one line.
    capsys.readouterr()
    bad = [f"data_root={models}", *MESH, "object=ball", "generate.model=fixed", "generate.touch_force=3.5"]
    assert main(["generate", *bad]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "model 'fixed' was not trained with force (generator.force=none)" in err[0]
    assert main(["generate", *bad[:-2], "generate.model=plane", "generate.touch_force=-2"]) == 1
    assert capsys.readouterr().err.strip() == "error: generate.touch_force: a force must be >= 0 N, got -2.0"


def test_a_force_the_sensor_cannot_press_is_one_line(models, capsys):
    # The Digit presses up to 20 N (sensor.force_range): a request above it is refused, not generated.
    _sphere_scene(models)
    gen = [f"data_root={models}", *MESH, "object=ball", "generate.model=plane", "generate.run_name=over"]
    capsys.readouterr()
    assert main(["generate", *gen, "generate.touch_force=1e9"]) == 1
    assert capsys.readouterr().err.strip().splitlines() == [
        "error: generate.touch_force: sensor 'digit': force must be in (0.0, 20.0] N, got 1000000000.0 "
        "(sensor.force_range)"
    ]
    assert not (models / "generated" / "over").exists()
    over = [*_base(models), "generator=tn_cgan_force", "evaluate.model=plane", "evaluate.classify.enabled=false"]
    assert main(["evaluate", *over, "evaluate.name=over", "evaluate.by_force.sweep=[1.0,100.0]"]) == 1
    assert capsys.readouterr().err.strip().splitlines() == [
        "error: evaluate.by_force.sweep: sensor 'digit': force must be in (0.0, 20.0] N, got 100.0 (sensor.force_range)"
    ]


def test_evaluate_reports_by_force_band_with_the_physical_check(models):
    from tnf.stages import evaluate

    over = [*_base(models), "generator=tn_cgan_force", "evaluate.model=plane", "evaluate.classify.enabled=false"]
    out = evaluate.run(compose("evaluate", [*over, "evaluate.per_object=null", "evaluate.name=force"]))
    f = out["results"]["force"]
    assert f["sweep"] == [1.0, 2.8, 4.6, 6.4, 8.2, 10.0]
    bands = f["novel_view"]["bands"]
    # Every band of the novel views holds touches (2 objects, one held out: 6 novel-view touches of the other).
    assert all(bands[b]["n"] >= 1 and 0 < bands[b]["ssim"] <= 1 for b in ("train", "interpolation", "extrapolation"))
    n = sum(bands[b]["n"] for b in ("train", "interpolation", "extrapolation", "outside") if b in bands)
    assert n == f["novel_view"]["area"]["n"] == f["novel_view"]["monotonic"]["n"]
    assert bands["adjacent"]["n"] <= bands["train"]["n"]  # training forces beside the interpolation band
    # The simulator pressed again at the sweep's forces: its contact area grows with the force.
    sim_area = f["figure"]["simulated_area"]
    assert all(b >= a for a, b in zip(sim_area, sim_area[1:], strict=False)) and sim_area[-1] > sim_area[0]
    # ... and on the figure split's poses pressed again, it grows on most (the generator's reference).
    assert f["simulator_monotonic"]["n"] == 6 and f["simulator_monotonic"]["share"] >= 0.5
    report = (models / "reports" / "force" / "report.md").read_text()
    assert "| simulator | area grows with force (reference, 6 poses pressed again) |" in report
    assert "## Evaluation by force" in report and "force_sweep.png" in report
    assert (models / "reports" / "force" / "runs" / "main_T-N_seed0" / "force_sweep.png").is_file()


def test_a_force_model_on_fixed_force_pairs_generates_at_touch_force(models, tmp_path):
    # Pairs made at one force (no force.npy): the model generates each test touch at touch.force, no bands.
    from tnf.stages import evaluate

    assert main(["pair", f"data_root={models}", *MESH, "pair.name=fixed-pairs"]) == 0
    assert "force" not in open_pairs(models / "pairs" / "fixed-pairs").manifest  # as before forces existed
    over = [*_base(models), "generator=tn_cgan_force", "evaluate.model=film", "evaluate.classify.enabled=false"]
    out = evaluate.run(compose("evaluate", [*over, "evaluate.dataset=fixed-pairs", "evaluate.name=fixed"]))
    assert "force" not in out["results"] and out["results"]["image"]["novel_view"]["T-N"]["n"] > 0


def test_a_force_model_on_pairs_of_one_recorded_force_is_scored_without_bands(models, tmp_path, capsys):
    # Pairs with force.npy from touches all pressed at touch.force (touch.force_range=null): scored, no bands.
    import shutil

    from tnf.stages import evaluate

    root = tmp_path / "tnf-data"
    for stage in ("capture", "touch", "pair"):
        assert main([stage, f"data_root={root}", *MESH, "pair.force=true"]) == 0
    assert not open_pairs(root / "pairs" / "digit-mesh").manifest["force"].get("range")
    shutil.copytree(models / "models" / "film", root / "models" / "film")
    over = [f"data_root={root}", *MESH, "pair.force=true", "generator=tn_cgan_force", "evaluate.model=film"]
    capsys.readouterr()
    out = evaluate.run(compose("evaluate", [*over, "evaluate.dataset=digit-mesh", "evaluate.classify.enabled=false"]))
    assert "force" not in out["results"] and out["results"]["image"]["novel_view"]["T-N"]["n"] > 0
    assert "were pressed at one force (touch.force_range=null)" in " ".join(capsys.readouterr().out.split())


def test_training_a_force_model_on_pairs_without_force_is_one_line(models, capsys):
    assert main(["pair", f"data_root={models}", *MESH, "pair.name=fixed-pairs"]) == 0
    capsys.readouterr()
    over = [f"data_root={models}", *MESH, "generator=tn_cgan_force", "data.datasets=[fixed-pairs]"]
    assert main(["train", *over, "train.run_name=no-force"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].endswith("the force comes with datasets made with pair.force=true")


def test_evaluate_takes_the_model_and_dataset_train_takes(models, capsys):
    # Neither evaluate.model, evaluate.dataset nor data.datasets: the model `tnf train` trains with these settings
    # (train.run_name=fixed) and the dataset `tnf pair` builds with them (digit-mesh), as `tnf generate` takes them.
    from tnf.stages import evaluate

    over = [f"data_root={models}", *MESH, *FORCE, "generator=tn_cgan", "train.run_name=fixed"]
    capsys.readouterr()
    out = evaluate.run(compose("evaluate", [*over, "evaluate.classify.enabled=false", "evaluate.name=defaults"]))
    assert out["results"]["model"] == "fixed" and out["results"]["image"]["novel_view"]["T-N"]["n"] > 0
    assert "evaluate.model not set: the model trained with these settings, fixed" in capsys.readouterr().out
