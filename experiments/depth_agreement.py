"""How closely the fitted scenes' depth crops match the ground-truth meshes', object by object.

    tnf pair experiment=sim_digit pair.scene_source=mesh        # the same touches, RGB-D from the meshes
    python experiments/depth_agreement.py --data-root tnf-data --fitted digit-hashgrid --mesh digit-mesh

Both datasets must pair the same touches (``tnf pair`` of one touch stage). Only pixels that the gel can reach
count: where the mesh's surface lies within ``--reach-mm`` behind the first contact. For each object it prints the
mean absolute depth difference there (mm; each crop's depth is measured from its own first-contact estimate, so
a shifted estimate counts too), the relief of the mesh's surface (the standard deviation of its depth
minus a 7 x 7 pixel local mean, mm: knurls, threads, dimples) and how much of that relief the fitted depth
reproduces (the correlation of the two local reliefs). A generator cannot draw relief that its input lacks.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from tnf.data.splits import SPLITS, split_code
from tnf.data.store import open_pairs
from tnf.errors import TnfError


def local_relief(depth: torch.Tensor, k: int = 7) -> torch.Tensor:
    """[B, H, W] depth minus its k x k local mean (edges replicated)."""
    x = depth[:, None]
    mean = F.avg_pool2d(F.pad(x, (k // 2,) * 4, mode="replicate"), k, stride=1)
    return (x - mean)[:, 0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data-root", default="tnf-data")
    ap.add_argument("--fitted", default="digit-hashgrid", help="paired dataset with RGB-D from the fitted scenes")
    ap.add_argument("--mesh", default="digit-mesh", help="the same touches paired with RGB-D from the meshes")
    ap.add_argument("--split", default="val", choices=list(SPLITS))
    ap.add_argument("--reach-mm", type=float, default=5.0, help="depth behind first contact that counts")
    args = ap.parse_args()

    root = Path(args.data_root) / "pairs"
    fit, mesh = open_pairs(root / args.fitted), open_pairs(root / args.mesh)
    window_mm = 1000 * float(mesh.manifest["preprocess"]["depth_window"])
    framing = [{k: v for k, v in d.manifest["preprocess"].items() if k != "crop_px"} for d in (fit, mesh)]
    if framing[0] != framing[1] or framing[0]["depth_norm"] != "contact":
        raise SystemExit(f"both datasets need the same framing, with depth_norm=contact: {framing}")
    code = split_code(args.split)
    print(f"{args.fitted} against {args.mesh}, {args.split} split; pixels within {args.reach_mm} mm of first contact")
    print(f"{'object':<16} {'pairs':>6} {'|diff| mm':>10} {'relief mm':>10} {'relief corr':>12}")
    for i, name in enumerate(mesh.objects):
        rows_m = np.flatnonzero((mesh.object_id == i) & (mesh.split == code))
        if name not in fit.objects:
            raise SystemExit(f"{args.fitted} has no pairs of {name}; pair both datasets from the same touches")
        j = fit.objects.index(name)
        rows_f = np.flatnonzero((fit.object_id == j) & (fit.split == code))
        if len(rows_m) == 0:
            continue
        if not np.array_equal(mesh.touch_index[rows_m], fit.touch_index[rows_f]):
            raise SystemExit(f"{name}: the two datasets pair different touches")
        dm = torch.from_numpy(np.asarray(mesh.depth[rows_m], np.float32)) * window_mm  # mm, contact at window / 2
        df = torch.from_numpy(np.asarray(fit.depth[rows_f], np.float32)) * window_mm
        near = dm <= window_mm / 2 + args.reach_mm
        rm, rf = local_relief(dm)[near], local_relief(df)[near]
        corr = float(torch.corrcoef(torch.stack([rm, rf]))[0, 1]) if len(rm) > 1 else float("nan")
        diff = float((dm - df).abs()[near].mean())
        print(f"{name:<16} {len(rows_m):>6} {diff:10.3f} {float(rm.std()):10.3f} {corr:12.3f}")


if __name__ == "__main__":
    try:
        main()
    except TnfError as e:  # a missing or unreadable dataset: one line, as the tnf command prints it
        raise SystemExit(f"error: {e}") from None
