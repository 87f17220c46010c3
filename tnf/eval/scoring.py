"""SSIM and MSE of a generator on a test set, per image, per object and overall, with the background baseline.

Batches are the paired datasets' dicts (float32 in [-1, 1]): ``rgb [B,3,128,128]``, ``depth [B,1,128,128]``,
``background [B,3,128,128]``, ``tactile [B,3,128,128]``, ``object_id [B]``. The generator is any callable
``batch -> [B,3,128,128]`` in [-1, 1]; the ``BG`` row uses ``batch["background"]`` as the prediction.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import torch

from tnf.eval.timing import Phases
from tnf.metrics import mse, ssim

BG = "BG"


class MetricAccumulator:
    """Collects per-image SSIM and MSE with each image's object, and summarises them."""

    def __init__(self) -> None:
        self.ssim: dict[str, list[float]] = defaultdict(list)
        self.mse: dict[str, list[float]] = defaultdict(list)

    def add(self, objects: Sequence[str], ssim_values: torch.Tensor, mse_values: torch.Tensor) -> None:
        for o, s, m in zip(objects, ssim_values.tolist(), mse_values.tolist(), strict=True):
            self.ssim[o].append(s)
            self.mse[o].append(m)

    def merge(self, other: MetricAccumulator) -> MetricAccumulator:
        out = MetricAccumulator()
        for acc in (self, other):
            for o in acc.ssim:
                out.ssim[o] += acc.ssim[o]
                out.mse[o] += acc.mse[o]
        return out

    def summary(self) -> dict[str, Any]:
        """``{"ssim": mean over images, "mse": ..., "n": images, "per_object": {object: {ssim, mse, n}}}``."""
        all_s = [v for vs in self.ssim.values() for v in vs]
        all_m = [v for vs in self.mse.values() for v in vs]
        n = len(all_s)
        return {
            "ssim": sum(all_s) / n if n else None,
            "mse": sum(all_m) / n if n else None,
            "n": n,
            "per_object": {
                o: {
                    "ssim": sum(self.ssim[o]) / len(self.ssim[o]),
                    "mse": sum(self.mse[o]) / len(self.mse[o]),
                    "n": len(self.ssim[o]),
                }
                for o in sorted(self.ssim)
            },
        }


def score_batches(
    batches: Iterable[Mapping[str, torch.Tensor]],
    generate: Callable[[Mapping[str, torch.Tensor]], torch.Tensor] | None,
    object_names: Sequence[str] | None = None,
    keep_examples: int = 0,
    on_batch: Callable[[], None] | None = None,
    phases: Phases | None = None,
    prefix: str = "",
) -> tuple[dict[str, MetricAccumulator], dict[str, torch.Tensor]]:
    """Score ``generate`` (None: the background baseline only) on ``batches``.

    Returns ({"G": accumulator, "BG": accumulator}, examples) where examples holds ``keep_examples`` touches
    spread over the objects (the first touch of each of the first objects seen, then their second, ...) on the
    CPU: rgb, depth, generated, target (the pair's touch; all in [-1, 1]) and object_id.

    ``phases`` (``tnf.eval.timing.Phases``) gets the seconds of ``<prefix>data`` (reading the batches),
    ``<prefix>generate`` and ``<prefix>metrics`` (SSIM, MSE, the examples).
    """
    timer = phases if phases is not None else Phases()
    accs = {"G": MetricAccumulator(), BG: MetricAccumulator()}
    # object id -> its first keep_examples touches, for the first keep_examples objects seen
    pools: dict[int, list[dict[str, torch.Tensor]]] = {}
    it = iter(batches)
    with torch.no_grad():
        while True:
            with timer.phase(prefix + "data"):
                batch = next(it, None)
            if batch is None:
                break
            with timer.phase(prefix + "generate"):
                fake = generate(batch).detach().float() if generate is not None else None
            with timer.phase(prefix + "metrics"):
                # Scored where the generator's images are (a GPU's images are not copied back to be scored).
                device = fake.device if fake is not None else batch["tactile"].device
                target = batch["tactile"].to(device)
                ids = batch["object_id"].tolist()
                objs = [object_names[i] if object_names is not None else str(i) for i in ids]
                bg = batch["background"].to(device)
                accs[BG].add(objs, ssim(bg, target), mse(bg, target))
                if fake is not None:
                    accs["G"].add(objs, ssim(fake, target), mse(fake, target))
                    _keep(pools, keep_examples, ids, batch, fake, target)
            if on_batch is not None:
                on_batch()
    rows = [p[r] for r in range(keep_examples) for p in pools.values() if r < len(p)][:keep_examples]
    return accs, {k: torch.stack([row[k] for row in rows]) for k in rows[0]} if rows else {}


def _keep(
    pools: dict[int, list[dict[str, torch.Tensor]]],
    keep_examples: int,
    ids: Sequence[int],
    batch: Mapping[str, torch.Tensor],
    fake: torch.Tensor,
    target: torch.Tensor,
) -> None:
    """Add the batch's touches to ``pools`` (object id -> its first ``keep_examples`` touches, for the first
    ``keep_examples`` objects seen), copied to the CPU."""
    for i, oid in enumerate(ids):
        if oid not in pools and len(pools) >= keep_examples:
            continue
        pool = pools.setdefault(oid, [])
        if len(pool) < keep_examples:
            row = {"rgb": batch["rgb"], "depth": batch["depth"], "generated": fake, "target": target}
            pool.append(
                {k: v[i].detach().to("cpu", copy=True) for k, v in row.items()} | {"object_id": torch.tensor(oid)}
            )
