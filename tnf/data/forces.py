"""The force of each pair's touch, for datasets made with ``pair.force=true`` (``force.npy``, newtons)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from tnf.errors import TnfError


@dataclass
class TouchForces:
    """Each object's touch forces (newtons, by touch index) and what the dataset manifest records of them."""

    by_object: dict[str, np.ndarray]
    record: dict[str, Any]

    def of(self, obj: str, touch_index: np.ndarray) -> np.ndarray:
        """float32 forces of ``obj``'s touches ``touch_index``."""
        return self.by_object[obj][np.asarray(touch_index, dtype=np.int64)].astype(np.float32)


def touch_forces(items: Mapping[str, Any]) -> TouchForces:
    """The recorded force of every touch of ``items`` (object -> ``TouchItem``); one-line TnfError for a touch
    without a finite, positive force, or objects whose touches come from different force ranges."""
    by_object: dict[str, np.ndarray] = {}
    plans = {}
    for obj, item in items.items():
        touches = item.touches
        out = np.zeros(max((t.index for t in touches), default=-1) + 1)
        for t in touches:
            f = t.force
            if isinstance(f, bool) or not isinstance(f, (int, float)) or not math.isfinite(f) or f <= 0:
                raise TnfError(
                    f"object {obj!r}: touch {t.index} in {item.folder / 'manifest.json'} records no positive "
                    f"force ({f!r}); pair.force needs touches made by `tnf touch`"
                )
            out[t.index] = float(f)
        by_object[obj] = out
        plans[obj] = item.manifest.get("force_range")
    distinct = {repr(v) for v in plans.values()}
    if len(distinct) > 1:
        raise TnfError(
            "pair.force: the objects' touches come from different force ranges "
            f"({'; '.join(f'{o}: {v}' for o, v in plans.items())}); rerun `tnf touch` with one touch.force_range"
        )
    plan = next(iter(plans.values()), None)
    return TouchForces(by_object, {"unit": "N", "range": plan})
