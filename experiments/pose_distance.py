"""Does a generator score worse on validation touches that lie far from every training touch of their object?

    python experiments/val_metrics.py --data-root tnf-data --per-pair val_pairs.csv RUN
    python experiments/pose_distance.py --data-root tnf-data --per-pair val_pairs.csv --column RUN

For each validation pair of ``--per-pair`` (written by ``experiments/val_metrics.py``) it finds, among the training
touches of the same object (the touch stage's manifest), the nearest contact point (mm) and the smallest angle
between sensor view axes (degrees). Objects differ in size and in how hard their touches are, so the
comparison is within each object: each touch's distance is ranked among its object's validation touches, and
its SSIM is taken relative to its object's mean. It prints, per distance quartile, the mean SSIM relative to
the object's mean, and the mean over objects of the rank correlation between SSIM and distance. Training
touches that the mirror augmentation adds (mirrored objects) are not counted. Touches far from the others can
also be easier ones (BG's SSIM follows the distance too): ``--control BG`` relates, instead of the SSIM, what is
left of it after a straight-line fit on BG's SSIM within each object.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from tnf.artifacts import MANIFEST, read_json
from tnf.errors import TnfError


def touch_poses(manifest: dict) -> dict[str, dict[int, tuple[np.ndarray, np.ndarray]]]:
    """Per split, touch index -> (contact point [3] in metres, sensor view axis [3], unit)."""
    out: dict[str, dict[int, tuple[np.ndarray, np.ndarray]]] = {}
    for t in manifest["touches"]:
        c2w = np.asarray(t["contact_c2w"], dtype=np.float64)
        axis = c2w[:3, 2] / np.linalg.norm(c2w[:3, 2])
        out.setdefault(t["split"], {})[int(t["index"])] = (np.asarray(t["contact_point"], dtype=np.float64), axis)
    return out


def nearest(points: np.ndarray, axes: np.ndarray, train_points: np.ndarray, train_axes: np.ndarray) -> np.ndarray:
    """[N, 2]: distance to the nearest training contact point (mm) and smallest view-axis angle (degrees)."""
    d = np.linalg.norm(points[:, None] - train_points[None], axis=-1).min(axis=1) * 1000.0
    cos = np.clip(axes @ train_axes.T, -1.0, 1.0).max(axis=1)
    return np.stack([d, np.degrees(np.arccos(cos))], axis=1)


def ranks(x: np.ndarray) -> np.ndarray:
    """Ranks 0..n-1 scaled to [0, 1] (ties broken by order; distances are continuous)."""
    r = np.empty(len(x))
    r[np.argsort(x, kind="stable")] = np.arange(len(x))
    return r / max(len(x) - 1, 1)


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    ra, rb = ranks(a) - 0.5, ranks(b) - 0.5
    denom = np.sqrt((ra**2).sum() * (rb**2).sum())
    return float((ra * rb).sum() / denom) if denom > 0 else 0.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data-root", default="tnf-data")
    ap.add_argument("--per-pair", required=True, help="CSV of experiments/val_metrics.py --per-pair")
    ap.add_argument("--column", required=True, help="the CSV column to relate to distance (a run)")
    ap.add_argument("--control", help="a column (BG) whose within-object linear fit is taken out of the SSIM first")
    ap.add_argument("--sensor", default="digit")
    ap.add_argument("--source", default="builtin")
    args = ap.parse_args()

    rows: dict[str, list[tuple[int, float, float]]] = {}
    with open(args.per_pair, newline="") as f:
        for r in csv.DictReader(f):
            for col in ("split", "object", "touch_index", args.column, args.control):
                if col is not None and col not in r:
                    raise SystemExit(f"no column {col!r} in {args.per_pair} (write it with val_metrics.py --per-pair)")
            if r["split"] != "val":
                raise SystemExit(f"{args.per_pair} holds {r['split']} pairs: this relates validation pairs only")
            control = float(r[args.control]) if args.control else 0.0
            rows.setdefault(r["object"], []).append((int(r["touch_index"]), float(r[args.column]), control))
    touch_root = Path(args.data_root) / "touch" / args.sensor / args.source
    quartile_sum = np.zeros((2, 4))
    quartile_n = np.zeros((2, 4))
    corr = []
    print(f"{'object':<16} {'pairs':>5} {'mm median':>9} {'deg median':>10} {'rho mm':>7} {'rho deg':>7}")
    for obj, pairs in sorted(rows.items()):
        poses = touch_poses(read_json(touch_root / obj / MANIFEST, f"touch manifest of {obj}"))
        train = list(poses.get("train", {}).values())
        missing = [i for i, _, _ in pairs if i not in poses.get("val", {})]
        if not train or missing:
            raise TnfError(
                f"the touches of {obj} under {touch_root} are not those the pairs were made from "
                f"({len(train)} training touches; validation touches missing: {missing[:5]})"
            )
        tp, ta = np.stack([p for p, _ in train]), np.stack([a for _, a in train])
        mine = [poses["val"][i] for i, _, _ in pairs]
        dist = nearest(np.stack([p for p, _ in mine]), np.stack([a for _, a in mine]), tp, ta)
        ssim = np.array([s for _, s, _ in pairs])
        if args.control:
            control = np.array([c for _, _, c in pairs])
            ssim = ssim - np.polyval(np.polyfit(control, ssim, 1), control)
        rel = ssim - ssim.mean()
        rho = [spearman(dist[:, k], ssim) for k in range(2)]
        corr.append(rho)
        for k in range(2):
            q = np.minimum((ranks(dist[:, k]) * 4).astype(int), 3)
            np.add.at(quartile_sum[k], q, rel)
            np.add.at(quartile_n[k], q, 1)
        med = np.median(dist, axis=0)
        print(f"{obj:<16} {len(pairs):>5} {med[0]:9.2f} {med[1]:10.2f} {rho[0]:7.2f} {rho[1]:7.2f}")
    c = np.array(corr)
    controlled = f", {args.control}'s fit taken out" if args.control else ""
    print(f"\n{args.column}{controlled}: {sum(len(p) for p in rows.values())} validation pairs, {len(rows)} objects")
    for k, name in enumerate(["contact point (mm)", "view axis (deg)"]):
        neg = int((c[:, k] < 0).sum())
        print(f"nearest training touch by {name}: mean rank correlation with SSIM {c[:, k].mean():+.3f} "
              f"({neg} of {len(c)} objects negative)")  # fmt: skip
        cells = "  ".join(f"Q{i + 1} {quartile_sum[k, i] / max(quartile_n[k, i], 1):+.4f}" for i in range(4))
        print(f"  SSIM minus the object's mean, by distance quartile (Q1 nearest): {cells}")


if __name__ == "__main__":
    try:
        main()
    except TnfError as e:  # a missing or foreign touch manifest: one line, as the tnf command prints it
        raise SystemExit(f"error: {e}") from None
