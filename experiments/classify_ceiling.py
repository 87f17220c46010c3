"""How much can added touches lift the classification task? Ground truth in place of generated images.

The evaluation's classification rows (``Sim``, ``Sim + G``) train on 20 simulated touches per object and test
on the novel-view touches. This script trains the same classifier (the experiment's ``evaluate.classifier``,
sim_digit's by default) on ground truth only, to show what a perfect generator could add:

- ``Sim``: the ``--sim-per-object`` training touches per object (as in the evaluation);
- ``Sim (all)``: every training touch (500 per object in sim_digit), all outside the novel-view cone;
- ``Sim + GT uniform``: ``Sim`` plus simulated touches from directions spread over the whole sphere, the
  distribution ``tnf generate`` samples its poses from (``--uniform``: a touch data root made with
  ``touch.novel_view_cone=0``, a different seed and no val or novel-view touches);
- ``GT uniform only``.

    tnf touch experiment=sim_digit                                            # TNF_DATA=A
    tnf touch experiment=sim_digit seed=1 touch.n_touches=200 touch.n_val=0 \\
        touch.n_novel_view=0 touch.novel_view_cone=0                         # TNF_DATA=B
    python experiments/classify_ceiling.py --data A --uniform B [--device cuda] [--seeds 0 1 2]

``Sim + GT uniform`` draws its batches as the experiment's evaluation does (sim_digit: half of each from
``Sim``, ``evaluate.classifier.real_fraction``); ``--real-fraction none`` or a number overrides it.
``--rows sim mixed`` trains only the two rows that this separates; each row is one classifier run per seed,
about 7 minutes on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


ROWS = ("sim", "all", "mixed", "added")


def _real_fraction(value: str) -> str:
    """``--real-fraction``: 'config', 'none' or a number (its range is checked with the classifier's config)."""
    if value not in ("config", "none"):
        try:
            float(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, 'none' or 'config', got {value!r}") from None
    return value


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="data root with touch/SENSOR/SOURCE/OBJECT/ (train, novel_view)")
    ap.add_argument("--uniform", required=True, help="data root with touches from the whole sphere (split train)")
    ap.add_argument("--sensor", default="digit")
    ap.add_argument("--source", default="builtin")
    ap.add_argument("--sim-per-object", type=int, help="default: the experiment's evaluate.classify.sim_per_object")
    ap.add_argument("--uniform-per-object", type=int, default=200)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--experiment", default="sim_digit", help="experiment whose evaluate.classifier is used")
    ap.add_argument(
        "--real-fraction",
        type=_real_fraction,
        default="config",
        help="share of each Sim + GT uniform batch drawn from Sim: a number, 'none' (uniform over the set) or "
        "'config' (the experiment's evaluate.classifier.real_fraction)",
    )
    ap.add_argument(
        "--rows",
        nargs="+",
        choices=ROWS,
        default=list(ROWS),
        help="rows to train (each costs one classifier run per seed): sim, all (every training touch), "
        "mixed (Sim + GT uniform), added (GT uniform only)",
    )
    a = ap.parse_args()

    import torch
    from hydra.errors import MissingConfigException
    from omegaconf import OmegaConf

    from tnf.errors import TnfError
    from tnf.eval.classify import ClassifierConfig, LabelledImages, load_touch_images, run_rows
    from tnf.testing import compose

    try:
        evaluate = compose("evaluate", [f"experiment={a.experiment}"]).evaluate
    except MissingConfigException as e:  # an unknown name; a broken experiment's own error is shown as it is
        raise TnfError(f"unknown experiment {a.experiment!r}; experiments: {', '.join(e.options or [])}") from None
    params = dict(OmegaConf.to_container(evaluate.classifier))
    if a.sim_per_object is None:
        a.sim_per_object = int(evaluate.classify.sim_per_object)
    if a.real_fraction != "config":
        params["real_fraction"] = None if a.real_fraction == "none" else float(a.real_fraction)
    cfg = ClassifierConfig.from_dict(params)
    print(f"classifier real_fraction: {cfg.real_fraction}")
    root = Path(a.data) / "touch" / a.sensor / a.source
    uroot = Path(a.uniform) / "touch" / a.sensor / a.source
    objects = sorted(p.name for p in root.iterdir() if (p / "manifest.json").is_file()) if root.is_dir() else []
    if len(objects) < 2:
        raise TnfError(f"need touches of at least 2 objects under {root}; run `tnf touch` first")
    if missing := [o for o in objects if not (uroot / o / "manifest.json").is_file()]:
        raise TnfError(f"no whole-sphere touches under {uroot} for {', '.join(missing)}; see the commands above")

    def load(folder: Path, split: str, limit: int | None = None, seed: int = 0, added: bool = False) -> LabelledImages:
        """Every object's touches of one split, labelled by the object's index; ``added``: they stand in for
        generated images (the classifier's ``real_fraction`` treats them as such)."""
        sets = []
        for label, o in enumerate(objects):
            x = load_touch_images(folder / o, cfg.image_size, [split], limit, seed)
            mark = torch.full((len(x),), added, dtype=torch.bool)
            sets.append(LabelledImages(x, torch.full((len(x),), label, dtype=torch.long), mark))
        return LabelledImages.concat(sets)

    # The full training set and the test set do not depend on the seed: loaded once.
    all_, test = load(root, "train"), load(root, "novel_view")
    results: dict[str, list[float]] = {}
    for seed in a.seeds:
        sim = load(root, "train", a.sim_per_object, seed)
        uniform = load(uroot, "train", a.uniform_per_object, seed, added=True)
        named = {
            "sim": (f"Sim ({a.sim_per_object}/object)", sim),
            "all": (f"Sim (all {len(all_) // len(objects)}/object)", all_),
            "mixed": (f"Sim + GT uniform ({a.uniform_per_object}/object)", LabelledImages.concat([sim, uniform])),
            "added": ("GT uniform only", uniform),
        }
        rows = dict(named[k] for k in ROWS if k in a.rows)
        acc = run_rows(rows, test, len(objects), cfg, seed, a.device)
        for row, v in acc.items():
            results.setdefault(row, []).append(v)
            print(f"seed {seed}  {row:32s} {v:5.1f} %  ({len(rows[row])} train images)", flush=True)
    print(f"\n{len(objects)} objects, {len(test)} novel-view test touches; mean over seeds {a.seeds}:")
    for row, vs in results.items():
        se = statistics.stdev(vs) / len(vs) ** 0.5 if len(vs) > 1 else 0.0
        print(f"  {row:32s} {statistics.mean(vs):5.1f} ± {se:.1f} %")


if __name__ == "__main__":
    from tnf.errors import TnfError

    try:
        main()
    except TnfError as e:  # missing or malformed touches: one line, as the tnf command prints it
        raise SystemExit(f"error: {e}") from None
