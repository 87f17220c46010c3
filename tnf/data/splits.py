"""The paper's evaluation splits and how touches are assigned to them.

- ``train`` / ``val``: touches of training objects that the simulator marked train / val;
- ``novel_view``: touches of training objects from the simulator's novel-view set (poses never trained on);
- ``novel_object``: every touch of a held-out object.

Assignment is per touch: all frames of one touch always land in the same split.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from tnf.errors import TnfError
from tnf.objects import TOUCH_SPLITS

SPLITS: tuple[str, ...] = ("train", "val", "novel_view", "novel_object")
"""Split names; a dataset stores each pair's split as its index in this tuple (int8)."""


def split_code(name: str) -> int:
    """Index of split ``name`` in ``SPLITS``; TnfError for an unknown name."""
    try:
        return SPLITS.index(name)
    except ValueError:
        raise TnfError(f"unknown split {name!r}; splits: {', '.join(SPLITS)}") from None


def choose_novel_objects(
    names: Sequence[str], novel_objects: Sequence[str] | None = None, num_novel: int = 3, seed: int = 0
) -> list[str]:
    """The held-out objects: ``novel_objects`` if given (validated), else ``num_novel`` drawn with ``seed``.

    The draw depends only on the sorted names and the seed, so it is the same on every machine.
    """
    names = sorted(names)
    if novel_objects is not None:
        missing = [n for n in novel_objects if n not in names]
        if missing:
            raise TnfError(f"pair.novel_objects: {missing[0]!r} is not among the objects ({', '.join(names)})")
        if len(set(novel_objects)) != len(novel_objects):
            raise TnfError(f"pair.novel_objects lists an object twice: {list(novel_objects)}")
        if len(novel_objects) == len(names):
            raise TnfError(
                f"pair.novel_objects holds out every selected object ({', '.join(names)}): none is left to train "
                "on; select more objects or hold out fewer"
            )
        return sorted(novel_objects)
    if num_novel < 0:
        raise TnfError(f"pair.num_novel_objects must be >= 0, got {num_novel}")
    if num_novel > len(names):
        raise TnfError(f"pair.num_novel_objects={num_novel} but only {len(names)} objects are selected")
    if num_novel == len(names):
        raise TnfError(
            f"pair.num_novel_objects={num_novel} holds out every selected object ({', '.join(names)}): none is "
            "left to train on; select more objects or set pair.num_novel_objects lower"
        )
    rng = np.random.default_rng(seed)
    picked: np.ndarray | list[int] = rng.choice(len(names), size=num_novel, replace=False) if num_novel else []
    return sorted(names[i] for i in picked)


def assign_splits(touch_splits: Sequence[str], novel_object: bool) -> np.ndarray:
    """int8 split codes for one object's touches (labels from the touch manifest)."""
    if novel_object:
        return np.full(len(touch_splits), split_code("novel_object"), dtype=np.int8)
    out = np.empty(len(touch_splits), dtype=np.int8)
    for i, s in enumerate(touch_splits):
        if s not in TOUCH_SPLITS:
            raise TnfError(f"touch {i} has split {s!r}; expected one of {', '.join(TOUCH_SPLITS)}")
        out[i] = SPLITS.index(s)
    return out
