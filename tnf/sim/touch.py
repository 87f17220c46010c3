"""Touch sampling: sensor start poses on a sphere around the object, pressed toward its centre.

Poses are camera-to-world 4x4 matrices in the OpenGL convention (the sensor looks along its -z axis, +y up),
metres, in the object's world frame (the same frame as the capture stage's cameras).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from tnf.cameras import look_at
from tnf.errors import TnfError
from tnf.sim.base import TouchBatch


def roll_about_view(c2w: np.ndarray, angle: float) -> np.ndarray:
    """Rotate a camera about its own view axis by ``angle`` radians."""
    c, s = np.cos(angle), np.sin(angle)
    rot = np.eye(4)
    rot[:2, :2] = [[c, -s], [s, c]]
    return c2w @ rot


def sphere_directions(
    rng: np.random.Generator, n: int, axis: Sequence[float], cone_deg: float, inside: bool
) -> np.ndarray:
    """``[n, 3]`` unit vectors uniform on the sphere, inside (or outside) a cone of half-angle ``cone_deg``
    around ``axis`` (rejection sampling). ``cone_deg == 0`` holds nothing out: the whole sphere either way."""
    if not 0.0 <= cone_deg < 180.0:
        raise TnfError(
            f"the held-out cone's half-angle (touch.novel_view_cone) must be in [0, 180) degrees, got {cone_deg}"
        )
    a = np.asarray(axis, dtype=np.float64)
    if a.shape != (3,) or not np.isfinite(a).all() or np.linalg.norm(a) == 0.0:
        raise TnfError(
            f"the held-out cone's axis (touch.novel_view_axis) must be a non-zero 3-vector, got {list(axis)}"
        )
    a = a / np.linalg.norm(a)
    cos_c = np.cos(np.radians(cone_deg))
    out: list[np.ndarray] = []
    while sum(len(o) for o in out) < n:
        v = rng.normal(size=(max(4 * n, 64), 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        ok = np.ones(len(v), bool) if cone_deg == 0 else (v @ a >= cos_c) if inside else (v @ a < cos_c)
        out.append(v[ok])
    return np.concatenate(out)[:n]


def start_poses(
    rng: np.random.Generator,
    directions: np.ndarray,
    radius: float,
    center: Sequence[float] = (0.0, 0.0, 0.0),
    up: Sequence[float] = (0.0, 0.0, 1.0),
    random_roll: bool = False,
    lateral: Sequence[float] = (0.0, 0.0),
) -> np.ndarray:
    """``[n, 4, 4]`` sensor poses at ``center + radius * direction``, looking at ``center``.

    ``lateral`` ``(x, y)``, metres: each pose then moves along its own image x and y axes by amounts drawn
    uniformly from ``[-x, x]`` and ``[-y, y]``, so that the press lands off the gel's centre (a small object's
    contact then appears anywhere on the gel, not only in the middle). ``(0, 0)`` draws nothing."""
    c = np.asarray(center, dtype=np.float64)
    half = np.asarray(lateral, dtype=np.float64)
    poses = []
    for d in directions:
        m = look_at(c + radius * d, c, up, fallback="parallel")
        if random_roll:
            m = roll_about_view(m, rng.uniform(0, 2 * np.pi))
        if half.any():
            dx, dy = rng.uniform(-half, half)
            m[:3, 3] += dx * m[:3, 0] + dy * m[:3, 1]
        poses.append(m)
    return np.stack(poses)


@dataclass
class Collected:
    """Touches that made contact: the simulator's outputs for them, their start poses and the misses."""

    start_c2w: np.ndarray
    results: Any  # TouchBatch of the kept touches
    discarded: int
    target_force: np.ndarray | None = None  # [n] target force of each kept touch, newtons (with a force sampler)


def collect(
    sim: Any,
    mesh: Any,
    n: int,
    rng: np.random.Generator,
    *,
    radius: float,
    force: float | Callable[[int], np.ndarray],
    batch_size: int,
    axis: Sequence[float],
    cone_deg: float,
    inside: bool,
    up: Sequence[float],
    random_roll: bool,
    seed: int,
    max_attempts: int,
    lateral: Sequence[float] = (0.0, 0.0),
) -> Collected:
    """Simulate touches in batches until ``n`` made contact; touches without contact are discarded and counted.

    ``force`` is every press's force (newtons), or a sampler ``k -> [k]`` forces called once per batch (each
    kept touch's target then comes back in ``target_force``). ``lateral``: the start poses' sideways spread
    (``start_poses``).

    Raises a TnfError when fewer than ``n`` touches hit after ``max_attempts * n`` tries.
    """

    kept: list[TouchBatch] = []
    starts: list[np.ndarray] = []
    targets: list[np.ndarray] = []
    got, discarded, tries, k = 0, 0, 0, 0
    while got < n:
        if tries >= max_attempts * max(n, 1):
            raise TnfError(
                f"only {got} of {n} touches reached the object after {tries} tries; "
                "check touch.radius against the object size (sensor must start outside and reach it)"
            )
        b = min(batch_size, max(n - got, 1))
        dirs = sphere_directions(rng, b, axis, cone_deg, inside)
        poses = start_poses(rng, dirs, radius, up=up, random_roll=random_roll, lateral=lateral)
        f = force(b) if callable(force) else force
        out = sim.press(mesh, poses, f, seed=seed * 100003 + k)
        k += 1
        tries += b
        keep = np.flatnonzero(out.hit)[: n - got]
        discarded += int((~out.hit).sum())
        kept.append(_take(out, keep))
        starts.append(poses[keep])
        targets.append(np.broadcast_to(np.asarray(f, dtype=np.float64), (b,))[keep])
        got += len(keep)
    target = np.concatenate(targets) if callable(force) else None
    return Collected(np.concatenate(starts), _concat(kept), discarded, target)


def _take(batch: Any, idx: np.ndarray) -> Any:
    from dataclasses import fields, replace

    return replace(batch, **{f.name: getattr(batch, f.name)[idx] for f in fields(batch)})


def _concat(batches: list[Any]) -> Any:
    from dataclasses import fields, replace

    return replace(
        batches[0], **{f.name: np.concatenate([getattr(b, f.name) for b in batches]) for f in fields(batches[0])}
    )
