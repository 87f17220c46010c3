"""SSIM and MSE of trained generator runs on a paired dataset's validation (or training) split, beside BG.

    python experiments/val_metrics.py --data-root tnf-data --dataset digit-hashgrid RUN [RUN ...] [--device cuda]

Each RUN is a folder under <data-root>/models/ (its best.ckpt is scored). Generators that keep dropout on when
generating are scored both ways (the row ``dropout off`` switches it off). This is how tn_cgan's defaults were
chosen (docs/decisions/): on the validation split, never on a test split.
``--split train`` scores the pairs a run trained on: how closely the generator fits them, apart from how it
generalises. ``--per-object`` adds each object's SSIM (one column per run, beside BG), to see where a mean is lost.
``--mirror-average`` also scores each run averaged with its own image of the mirrored touch (the row ``mirror
avg``; ``GeneratorSystem.generate(batch, mirror)``), for sensors with a mirror symmetry. ``--per-pair FILE``
writes every pair's SSIM per column to a CSV (split, object, touch index in its touch item), for analyses such as
``experiments/pose_distance.py``. Runs trained with a weight average (``train.ema_decay``) are scored with it; their
rows ``no average`` (and ``no avg, mirror avg``) score the same checkpoint's weights as trained. ``--ensemble`` adds
the row of the mean image of all runs (mirror-averaged too with ``--mirror-average``): what averaging independent
models would give. Datasets made with ``pair.prior=true`` add the row ``prior``: the simulator's image of each
depth crop, scored as it is (``tnf.data.prior``).
"""

from __future__ import annotations

import argparse
import csv
import functools
import json
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from tnf import metrics
from tnf.data import PairDataset, collate_pairs, sensor_mirror, training_order
from tnf.errors import TnfError
from tnf.generators import load_generator
from tnf.generators.nets.gan import NoiseDropout
from tnf.generators.system import AVERAGE_PREFIX, read_checkpoint


def score(generate, loader: DataLoader, device: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-pair SSIM, MSE and object id, in the loader's order."""
    ssim, mse, obj = [], [], []
    for batch in loader:
        obj.append(batch["object_id"])
        batch = {k: v.to(device) for k, v in batch.items()}
        fake = generate(batch)
        ssim.append(metrics.ssim(fake, batch["tactile"]).cpu())
        mse.append(metrics.mse(fake, batch["tactile"]).cpu())
    return torch.cat(ssim), torch.cat(mse), torch.cat(obj)


def per_object_table(columns: dict[str, torch.Tensor], object_id: torch.Tensor, names: list[str]) -> str:
    """Mean SSIM per object (rows) for each column's per-pair SSIM, lowest BG first."""
    present = [i for i in range(len(names)) if bool((object_id == i).any())]
    means = {c: {i: float(v[object_id == i].mean()) for i in present} for c, v in columns.items()}
    order = sorted(present, key=lambda i: means["BG"][i]) if "BG" in means else present
    lines = [f"{'object':<16}" + "".join(f" {c[:14]:>14}" for c in columns)]
    lines += [f"{names[i]:<16}" + "".join(f" {means[c][i]:14.4f}" for c in columns) for i in order]
    return "\n".join(lines)


def write_per_pair(
    path: Path, columns: dict[str, torch.Tensor], ds: PairDataset, object_id: torch.Tensor, split: str
) -> None:
    """One row per pair in the split's order: split, object, touch index within its touch item, SSIM per column."""
    touch_index = np.asarray(ds.arrays.touch_index)[ds.index]
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["split", "object", "touch_index", *columns])
        for i in range(len(ds)):
            ssim = [f"{float(v[i]):.5f}" for v in columns.values()]
            w.writerow([split, ds.object_names[int(object_id[i])], int(touch_index[i]), *ssim])
    print(f"per-pair SSIM: {path}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="*", help="run folders under <data-root>/models/ (none: BG and prior only)")
    ap.add_argument("--data-root", default="tnf-data")
    ap.add_argument("--dataset", default="digit-hashgrid", help="paired dataset under <data-root>/pairs/")
    ap.add_argument("--split", default="val", choices=["val", "train"], help="never a test split")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--per-object", action="store_true", help="also each object's SSIM per run")
    ap.add_argument("--mirror-average", action="store_true", help="also each run averaged with its mirror")
    ap.add_argument("--per-pair", metavar="FILE", help="write each pair's SSIM per column to this CSV")
    ap.add_argument("--ensemble", action="store_true", help="also the mean image of all runs")
    args = ap.parse_args()
    if args.ensemble and len(args.runs) < 2:
        ap.error("--ensemble averages the images of several runs: give at least two")

    root = Path(args.data_root)
    missing = [r for r in args.runs if not (root / "models" / r / "best.ckpt").is_file()]
    if missing:
        raise SystemExit(f"no best.ckpt under {root / 'models'} for: {', '.join(missing)}")
    # Object ids as the first run was trained with (a surface field knows objects by their training ids).
    first = root / "models" / args.runs[0] / "manifest.json"
    trained = json.loads(first.read_text()).get("object_names") if first.is_file() else None
    own = json.loads((root / "pairs" / args.dataset / "manifest.json").read_text())["objects"]
    names = training_order(trained, own)
    ds = PairDataset(root / "pairs" / args.dataset, [args.split], object_names=names)
    if len(ds) == 0:
        raise SystemExit(f"dataset {args.dataset} has no {args.split} pairs")
    loader = DataLoader(ds, batch_size=args.batch, shuffle=False, collate_fn=collate_pairs)
    mirror = sensor_mirror(ds.manifest, root / "pairs" / args.dataset) if args.mirror_average else None
    print(f"{args.dataset} {args.split}: {len(ds)} pairs, device {args.device}")
    print(f"{'run':<28} {'generation':<20} {'SSIM':>7} {'MSE':>7}")
    columns: dict[str, torch.Tensor] = {}
    systems = []
    for run in args.runs:
        ckpt = root / "models" / run / "best.ckpt"
        system = load_generator(ckpt, args.device)
        if args.ensemble:
            systems.append(system)
        drops = [m for m in system.modules() if isinstance(m, NoiseDropout)]
        trained = [d.always_on for d in drops]
        modes = [("as trained", None, None)]
        modes += [("dropout off", False, None)] if any(d.always_on for d in drops) else []
        modes += [("mirror avg", None, mirror)] if mirror is not None else []
        if any(k.startswith(AVERAGE_PREFIX) for k in read_checkpoint(ckpt)["state_dict"]):
            weights = load_generator(ckpt, args.device, averaged=False)
            for label, mirror_order in [("no average", None)] + ([("no avg, mirror avg", mirror)] if mirror else []):
                torch.manual_seed(0)
                s, m, _ = score(functools.partial(weights.generate, mirror=mirror_order), loader, args.device)
                print(f"{run:<28} {label:<20} {s.mean():7.4f} {m.mean():7.1f}")
                columns[f"{run} ({label})"] = s
            del weights
        for label, on, mirror_order in modes:
            for d, as_trained in zip(drops, trained, strict=True):
                d.always_on = as_trained if on is None else on
            torch.manual_seed(0)
            s, m, _ = score(functools.partial(system.generate, mirror=mirror_order), loader, args.device)
            print(f"{run:<28} {label:<20} {s.mean():7.4f} {m.mean():7.1f}")
            columns[run if label == "as trained" else f"{run} ({label})"] = s
    if args.ensemble:
        for label, mirror_order in [("ensemble", None)] + ([("ensemble, mirror", mirror)] if mirror else []):

            def mean_image(batch, order=mirror_order):
                return torch.stack([g.generate(batch, order) for g in systems]).mean(0)

            torch.manual_seed(0)
            s, m, _ = score(mean_image, loader, args.device)
            print(f"{f'{len(systems)} runs':<28} {label:<20} {s.mean():7.4f} {m.mean():7.1f}")
            columns[label] = s
    s, m, object_id = score(lambda b: b["background"], loader, args.device)
    print(f"{'BG':<28} {'-':<20} {s.mean():7.4f} {m.mean():7.1f}")
    columns["BG"] = s
    if ds.arrays.prior is not None:  # pair.prior: the simulator's image of the depth crop, as it is
        s, m, _ = score(lambda b: b["prior"], loader, args.device)
        print(f"{'prior':<28} {'-':<20} {s.mean():7.4f} {m.mean():7.1f}")
        columns["prior"] = s
    if args.per_pair:
        write_per_pair(Path(args.per_pair), columns, ds, object_id, args.split)
    if args.per_object:
        print(f"\nSSIM per object ({args.split} split)")
        print(per_object_table(columns, object_id, ds.object_names))


if __name__ == "__main__":
    try:
        main()
    except TnfError as e:  # a bad dataset or checkpoint: one line, as the tnf command prints it
        raise SystemExit(f"error: {e}") from None
