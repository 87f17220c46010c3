"""Few-shot fine-tuning on real presses: the paper's Table 2 with the GelSight Mini's real frames.

Run after ``tnf pipeline experiment=sim_gelsight_mini data_root=ROOT`` (its T-N model and its calibration):

    python experiments/real_finetune.py --data-root ROOT --out OUT select   # choose steps and lr
    python experiments/real_finetune.py --data-root ROOT --out OUT final    # train on 0-15, score 16-23

The rule, fixed before any run. T-N (fine-tuned from the simulator-trained model) chooses its learning rate
(the generator's own, or a quarter of it) and its training batches (25, 50, 100 or 200 batches of up to 16
pairs: the experiment's data.batch_size, so every training press in one batch) on the training presses alone:
fine-tuned on presses 0-11, scored on presses 12-15 by the mean SSIM of the 4r crop at the recording's 640x480;
the highest wins, and of candidates within 0.002 of it the fewest batches. As in the paper's Table 2, FS (the
same network from scratch) and T-N + sim (T-N with 16 training pairs of the pipeline's simulated dataset in the
mix) train with T-N's chosen setting. Each is then trained on presses 0-15 and scored once on presses 16-23.
Every run: the depth measured from the pressed gel (``reference=gel``), the calibration's depth factor, seed 0.

A supplementary row, fixed before any FS run: FS with its own choice by the same rule (``select-fs``), among the
same learning rates and 25 to 800 batches, since a network from scratch may need more batches than T-N.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from tnf.artifacts import read_json
from tnf.real import realism, report
from tnf.real.finetune import finetune_on_presses
from tnf.real.generated import checkpoint_framing, generate_presses
from tnf.real.presses import at_sensor_size, resolve_presses
from tnf.registry import SENSORS

FIT, CHOOSE = list(range(12)), [12, 13, 14, 15]
TRAIN, TEST = list(range(16)), list(range(16, 24))
STEPS = (25, 50, 100, 200)
FS_STEPS = (25, 50, 100, 200, 400, 800)
BATCH = 16
LR_FACTORS = (1.0, 0.25)
TIE = 0.002
SIM_PAIRS = 16
METHODS = ("T-N", "FS", "T-N + sim")


def setup(root: Path, model: str, calibration: str) -> dict:
    """The pipeline's checkpoint, its generator spec and framing, the calibrated sensor and the presses."""
    import torch

    from tnf.generators.names import find_run

    model = find_run(root / "models", model) or model  # a run family names its one finished run
    ckpt = root / "models" / model / "best.ckpt"
    cal = root / "calibration" / "gelsight_mini" / calibration
    sensor = SENSORS.build({"name": "gelsight_mini", "width": 160, "height": 120, "calibration": str(cal)})
    depth_scale = float(read_json(cal / "realism.json", "realism")["fit"]["depth_scale"])
    spec = torch.load(ckpt, weights_only=False, map_location="cpu")["tnf"]["generator"]
    sim = root / "pairs" / read_json(root / "models" / model / "manifest.json", "model")["datasets"][0]
    return {
        "ckpt": ckpt,
        "spec": dict(spec),
        "framing": checkpoint_framing(ckpt),
        "sensor": sensor,
        "presses": resolve_presses("taxim:gelsight_mini", root),
        "depth_scale": depth_scale,
        "sim": sim,
    }


def train(s: dict, method: str, train: list[int], out: Path, steps: int, factor: float) -> tuple[Path, float]:
    """One fine-tuning run; returns the checkpoint and its wall seconds."""
    t0 = time.perf_counter()
    ckpt = finetune_on_presses(
        None if method == "FS" else s["ckpt"],
        s["presses"],
        s["sensor"],
        train,
        out,
        steps,
        lr=float(s["spec"].get("lr", 2e-4)) * factor,
        batch_size=BATCH,
        generator=s["spec"],
        framing=s["framing"],
        depth_scale=s["depth_scale"],
        sim=s["sim"] if method == "T-N + sim" else None,
        sim_pairs=SIM_PAIRS if method == "T-N + sim" else 0,
    )
    return ckpt, time.perf_counter() - t0


def score(s: dict, ckpt: Path, presses: list[int], reference: str = "gel") -> dict:
    sp = at_sensor_size(s["presses"], s["sensor"], presses)
    images = generate_presses(ckpt, s["sensor"], sp, s["presses"].radius_mm * 1e-3, s["depth_scale"],
                              framing=s["framing"], reference=reference)  # fmt: skip
    return scored(images, s["presses"], sp)


def scored(images: np.ndarray, presses, sp) -> dict:
    """``{"per_press": {metric: [N]}, "mean": {metric: float}}`` of ``images`` against the real frames."""
    per = report.score_rows([report.Row("images", images)], presses, sp)
    return {"per_press": per["images"], "mean": report.mean_scores(per)["images"]}


def select(s: dict, out: Path, method: str = "T-N", grid: tuple[int, ...] = STEPS) -> dict:
    rows = []
    tag = "" if method == "T-N" else "_fs"
    for factor in LR_FACTORS:
        for steps in grid:
            ckpt, seconds = train(s, method, FIT, out / f"select{tag}" / f"lr{factor:g}_s{steps}", steps, factor)
            m = score(s, ckpt, CHOOSE)["mean"]
            rows.append({"lr_factor": factor, "steps": steps, "seconds": seconds, **m})
            print(
                f"{method} lr x{factor:g} {steps} batches: crop SSIM {m['ssim_crop']:.4f}, {seconds:.0f} s", flush=True
            )
    best = max(r["ssim_crop"] for r in rows)
    pick = min((r for r in rows if r["ssim_crop"] >= best - TIE), key=lambda r: (r["steps"], -r["ssim_crop"]))
    record = {"candidates": rows, "choice": {"steps": pick["steps"], "lr_factor": pick["lr_factor"]}}
    print(f"{method}: chose {pick['steps']} batches at lr x{pick['lr_factor']:g}")
    (out / f"select{tag}.json").write_text(json.dumps(record, indent=2))
    return record


def final(s: dict, out: Path) -> None:
    chosen = json.loads((out / "select.json").read_text())
    means, seconds, record = {}, {}, {}
    sp = at_sensor_size(s["presses"], s["sensor"], TEST)
    simulated, _ = realism.render(
        s["sensor"], {"name": "warp_gel"}, sp, s["presses"].radius_mm * 1e-3, s["depth_scale"]
    )
    means["calibrated simulator"] = scored(simulated, s["presses"], sp)["mean"]
    background = np.repeat(sp.background[None], len(TEST), 0)
    means["background (no contact)"] = scored(background, s["presses"], sp)["mean"]
    t0 = time.perf_counter()
    means["T-N (simulator only)"] = score(s, s["ckpt"], TEST)["mean"]
    seconds["T-N (simulator only)"] = time.perf_counter() - t0
    means["T-N (simulator only), depth from the first contact"] = score(s, s["ckpt"], TEST, "contact")["mean"]
    c = chosen["choice"]
    for method in METHODS:
        name = method.replace(" ", "").replace("+", "plus")
        ckpt, secs = train(s, method, TRAIN, out / "final" / name, int(c["steps"]), float(c["lr_factor"]))
        label = f"{method} ({c['steps']} batches, lr x{c['lr_factor']:g})"
        result = score(s, ckpt, TEST)
        means[label], seconds[label], record[label] = result["mean"], secs, result
    if (out / "select_fs.json").is_file():
        c = json.loads((out / "select_fs.json").read_text())["choice"]
        ckpt, secs = train(s, "FS", TRAIN, out / "final" / "FS_own", int(c["steps"]), float(c["lr_factor"]))
        label = f"FS, its own choice ({c['steps']} batches, lr x{c['lr_factor']:g})"
        result = score(s, ckpt, TEST)
        means[label], seconds[label], record[label] = result["mean"], secs, result
    (out / "final.json").write_text(json.dumps({"mean": means, "seconds": seconds, "runs": record}, indent=2))
    print(report.table(means))
    print("training seconds: " + ", ".join(f"{k} {v:.0f}" for k, v in seconds.items()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("phase", choices=("select", "select-fs", "final"))
    ap.add_argument("--data-root", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--model", default="tn_cgan_plain-gelsight_mini-hashgrid-seed0", help="a run, or its family")
    ap.add_argument("--calibration", default="mini_160x120")
    a = ap.parse_args()
    s = setup(a.data_root, a.model, a.calibration)
    a.out.mkdir(parents=True, exist_ok=True)
    if a.phase == "select":
        select(s, a.out)
    elif a.phase == "select-fs":
        select(s, a.out, "FS", FS_STEPS)
    else:
        final(s, a.out)


if __name__ == "__main__":
    main()
