"""Shared helpers of the reliability tests: run the real `tnf` command, make bad inputs, inspect the store."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
QUIET = ["debug=tiny", "progress=false"]


def run_tnf(capsys, *args: str) -> tuple[int, str]:
    """``tnf ARGS`` in this process: (exit code, the one ``error:`` line, or all of stderr when there is none)."""
    from tnf.cli import main

    capsys.readouterr()
    rc = main([*args])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    return rc, lines[0] if len(lines) == 1 else err


def finished_items(root: Path, stage: str) -> list[Path]:
    """Item folders of ``stage`` that carry a manifest (finished items).

    Safe to poll while a stage runs: a ``.partial`` folder renamed into place while the walk lists it makes the
    walk fail, and it is then walked again."""
    base = root / stage
    for _ in range(10):
        try:
            return sorted(m.parent for m in base.rglob("manifest.json")) if base.is_dir() else []
        except FileNotFoundError:
            continue
    return []


def partials(root: Path) -> list[Path]:
    """Temporary folders of unfinished items anywhere in the store."""
    return sorted(root.rglob("*.partial")) if root.is_dir() else []


def assert_nothing_written(root: Path, stage: str) -> None:
    """No finished item and no temporary folder of ``stage`` is left in the store."""
    assert finished_items(root, stage) == [], finished_items(root, stage)
    assert partials(root) == [], partials(root)


# -- meshes as bytes --------------------------------------------------------------------------------------
def cube_obj(size: float = 0.05) -> str:
    """A closed cube of edge ``size`` metres as OBJ text."""
    h = size / 2
    v = [(x, y, z) for x in (-h, h) for y in (-h, h) for z in (-h, h)]
    f = [(1, 2, 4), (1, 4, 3), (5, 7, 8), (5, 8, 6), (1, 5, 6), (1, 6, 2), (3, 4, 8), (3, 8, 7), (1, 3, 7), (1, 7, 5),
         (2, 6, 8), (2, 8, 4)]  # fmt: skip
    return "".join(f"v {a} {b} {c}\n" for a, b, c in v) + "".join(f"f {a} {b} {c}\n" for a, b, c in f)


def tetra_obj(flip: bool = False, offset: float = 0.0) -> tuple[list[str], list[str]]:
    """A tetrahedron's OBJ vertex and face lines (faces inward when ``flip``), vertex indices from 1."""
    v = [(0, 0, 0), (0.05, 0, 0), (0, 0.05, 0), (0, 0, 0.05)]
    f = [(1, 3, 2), (1, 2, 4), (1, 4, 3), (2, 3, 4)]
    if flip:
        f = [(a, c, b) for a, b, c in f]
    return [f"v {x + offset} {y} {z}\n" for x, y, z in v], [f"f {a} {b} {c}\n" for a, b, c in f]


def zero_volume_obj() -> str:
    """Two closed tetrahedra, one turned inside out: watertight, not flat, but of zero total volume."""
    v1, f1 = tetra_obj()
    v2, f2 = tetra_obj(flip=True, offset=0.1)
    f2 = ["f " + " ".join(str(int(i) + 4) for i in ln.split()[1:]) + "\n" for ln in f2]
    return "".join(v1 + v2 + f1 + f2)


# -- subprocesses that get killed -------------------------------------------------------------------------
def tnf_env(root: Path) -> dict[str, str]:
    env = dict(os.environ)
    env.update(
        TNF_DATA=str(root),
        PYOPENGL_PLATFORM="egl",
        WARP_CACHE_PATH=str(REPO / ".warp-cache"),
        OMP_NUM_THREADS="1",
        WANDB_MODE="offline",
    )
    return env


def tnf_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "tnf.cli", *args]


def run_to_end(root: Path, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    out = subprocess.run(tnf_cmd(*args), env=tnf_env(root), capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, out.stderr[-3000:]
    return out


def kill_when(
    root: Path, args: tuple[str, ...], ready, timeout: float = 300, poll: float = 0.002, pause: bool = False
) -> bool:
    """Start ``tnf ARGS``, SIGKILL it as soon as ``ready()`` is true; False when it finished first.

    Some kill points last only milliseconds (an item's temporary folder while its files are written): poll often.
    ``pause``: stop the command (SIGSTOP) while ``ready()`` runs, for conditions slower than what they watch (loading
    a checkpoint): on a busy machine the command could otherwise finish while the condition is still reading."""
    p = subprocess.Popen(
        tnf_cmd(*args), env=tnf_env(root), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
    )
    t0 = time.monotonic()
    try:
        while p.poll() is None:
            if pause:
                os.killpg(p.pid, signal.SIGSTOP)
            if ready():
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
                return True
            if pause:
                os.killpg(p.pid, signal.SIGCONT)
            if time.monotonic() - t0 > timeout:
                raise TimeoutError(f"tnf {' '.join(args)} did not reach the kill point in {timeout} s")
            time.sleep(poll)
        return False
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


def tree_bytes(folder: Path, skip=("manifest.json",)) -> dict[str, bytes]:
    """Relative path -> content of every file under ``folder`` (but ``skip``), for exact comparisons."""
    return {
        str(p.relative_to(folder)): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name not in skip
    }


def same_arrays(a: Path, b: Path, rounding: bool = False) -> None:
    """The ``.npy`` files under two folders are equal.

    ``rounding``: uint8 images may differ by one level in at most one element in 10,000 (a rendered value that
    lands on a rounding boundary can round either way in another process); a resume that mixed up touches or
    rows changes far more than that. Other arrays must be equal.
    """
    names = sorted(str(p.relative_to(a)) for p in a.rglob("*.npy"))
    assert names == sorted(str(p.relative_to(b)) for p in b.rglob("*.npy"))
    for n in names:
        x, y = np.load(a / n), np.load(b / n)
        if rounding and x.dtype == np.uint8 and x.shape == y.shape:
            diff = np.abs(x.astype(np.int16) - y.astype(np.int16))
            assert diff.max() <= 1 and (diff > 0).mean() <= 1e-4, f"{n}: {int((diff > 0).sum())} elements differ"
        else:
            np.testing.assert_array_equal(x, y, err_msg=n)


# -- what a killed run leaves behind -----------------------------------------------------------------------
def leftovers(root: Path) -> list[Path]:
    """Temporary things of unfinished writes anywhere in the store: item folders (``*.partial``), atomic-write
    files (``.*.tmp``) and replaced items not yet removed (``.*.old-<pid>``)."""
    if not root.is_dir():
        return []
    return sorted({*root.rglob("*.partial"), *root.rglob(".*.tmp"), *root.rglob(".*.old-*")})


def copy_stages(src: Path, dst: Path, *stages: str) -> None:
    """Copy the folders of ``stages`` from store ``src`` to store ``dst``, keeping modification times (some
    config hashes record a checkpoint's mtime)."""
    import shutil

    for stage in stages:
        shutil.copytree(src / stage, dst / stage, dirs_exist_ok=True)


def manifest_stamps(root: Path, *stages: str) -> dict[Path, tuple[int, str]]:
    """Manifest path -> (mtime in ns, its ``created`` field) of every finished item of ``stages``."""
    import json

    out = {}
    for stage in stages:
        for folder in finished_items(root, stage):
            m = folder / "manifest.json"
            out[m] = (m.stat().st_mtime_ns, json.loads(m.read_text()).get("created"))
    return out


def assert_not_rewritten(stamps: dict[Path, tuple[int, str]]) -> None:
    """The manifests of ``stamps`` (see ``manifest_stamps``) are the same files as then: not recomputed."""
    import json

    for path, (mtime, created) in stamps.items():
        assert path.stat().st_mtime_ns == mtime, f"{path} was rewritten"
        assert json.loads(path.read_text()).get("created") == created, f"{path} was rewritten"
