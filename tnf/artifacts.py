"""The artifact store: how stages hand work to each other on disk.

Layout: ``<data_root>/<stage>/<item...>/`` with a ``manifest.json`` in each item folder that records the
config that produced it. An item is *done* when its manifest exists and its config matches; a stage skips
done items and recomputes the rest. An item is written into a temporary sibling folder and renamed into
place only when complete (manifest last), so an interrupted stage never leaves a folder that looks
finished, and parallel jobs writing different items never clobber each other.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import functools
import glob
import hashlib
import json
import logging
import os
import re
import shutil
import socket
import tempfile
import time
import uuid
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from tnf import __version__
from tnf.errors import TnfError
from tnf.registry import IDENTITY

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
DEFAULT_ROOT = "./tnf-data"

CACHE_VERSION = 2
"""The version of everything tnf writes to the artifact store: items, paired datasets, model checkpoints. It is
part of every artifact's key (``config_hash``), so raising it makes each stage redo what an earlier version wrote;
a checkpoint or dataset of another version is refused in one line."""


def data_root(configured: str | os.PathLike[str] | None = None) -> Path:
    """The artifact root: the config's value if given, else ``$TNF_DATA``, else ``./tnf-data``."""
    if configured not in (None, ""):
        return Path(str(configured)).expanduser().absolute()
    return Path(os.environ.get("TNF_DATA", DEFAULT_ROOT)).expanduser().absolute()


def config_hash(config: Mapping[str, Any]) -> str:
    """A stable hash of a JSON-able config (key order does not matter; settings dataclasses by ``identity``)."""
    keyed = {"cache_version": CACHE_VERSION, "config": _jsonable(config)}
    blob = json.dumps(keyed, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def identity(settings: Any) -> Any:
    """What of ``settings`` makes an artifact what it is, as plain data: a dataclass becomes a dict of its fields
    without those whose metadata says ``identity: False`` (``tnf.registry.IDENTITY``: a batch size, a device, a
    redo switch) or names a test that the settings fail (a setting that only matters with another's value),
    nested dataclasses, mappings and lists likewise. Every artifact key (``config_hash``) and every manifest's
    ``config`` is built from this."""
    return _jsonable(settings)


def _in_identity(field: dataclasses.Field[Any], settings: Any) -> bool:
    rule = field.metadata.get(IDENTITY, True)
    return bool(rule(settings)) if callable(rule) else bool(rule)


def _jsonable(x: Any) -> Any:
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {f.name: _jsonable(getattr(x, f.name)) for f in dataclasses.fields(x) if _in_identity(f, x)}
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf

        if isinstance(x, (DictConfig, ListConfig)):
            x = OmegaConf.to_container(x, resolve=True)
    except ImportError:  # pragma: no cover
        pass
    if isinstance(x, Mapping):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, Path):
        return str(x)
    if hasattr(x, "item") and callable(x.item):  # numpy / torch scalars
        return x.item()
    return x


def write_json(path: str | os.PathLike[str], data: Any) -> None:
    """Write JSON atomically (temporary file in the same folder, fsync, rename)."""
    write_bytes(path, (json.dumps(_jsonable(data), indent=2) + "\n").encode())


def write_bytes(path: str | os.PathLike[str], data: bytes | memoryview) -> None:
    """Write bytes atomically: readers see the old file or the whole new one, never a part."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # A killed earlier write of this file left its temporary file: remove it, as this write replaces it.
    for stale in path.parent.glob(f".{glob.escape(path.name)}.*.tmp"):
        if not _writer_alive(stale):
            stale.unlink(missing_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{_writer_tag()}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        # mkstemp makes the file private (0600); give it the permissions a plain open() would.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if _disk_full(e):
            raise DiskFull(
                f"{_reason(e)} writing {path}: it needs {_mb(len(data))} MB; "
                f"free space there: {_mb(free_bytes(path.parent))} MB"
            ) from None
        raise


class DiskFull(TnfError):
    """The disk (or the user's quota) filled while tnf wrote a file (``item`` false) or an item (true)."""

    def __init__(self, message: str, item: bool = False):
        super().__init__(message)
        self.item = item


_DISK_FULL_ERRNOS = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)}


def _disk_full(e: BaseException) -> bool:
    """Whether ``e`` says the disk or the quota is full (an item's error, already worded, is not re-worded)."""
    if isinstance(e, DiskFull):
        return not e.item
    return isinstance(e, OSError) and e.errno in _DISK_FULL_ERRNOS


def _reason(e: BaseException) -> str:
    """``no space left on device`` or ``disk quota exceeded``, from a disk-full error."""
    if isinstance(e, OSError) and e.errno is not None:
        return (e.strerror or os.strerror(e.errno)).lower()
    return "no space left on device"


def _mb(n: int | None) -> str:
    return "?" if n is None else f"{n / 1e6:.1f}"


def free_bytes(path: str | os.PathLike[str]) -> int | None:
    """Free space for an unprivileged user on the file system of ``path`` (or of its nearest existing folder)."""
    p = Path(path).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        return shutil.disk_usage(p).free
    except OSError:
        return None


def require_space(path: str | os.PathLike[str], needed: int, what: str) -> None:
    """A TnfError, before any work, when the file system of ``path`` has less than ``needed`` bytes free."""
    free = free_bytes(path)
    if free is not None and free < needed:
        raise TnfError(
            f"not enough space for {what}: it needs about {_mb(needed)} MB; free space there: {_mb(free)} MB"
        )


def _tree_bytes(folder: Path) -> int:
    """Total size of the files under ``folder`` (what a write put there before it failed)."""
    total = 0
    for dirpath, _, files in os.walk(folder):
        for f in files:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(dirpath, f)).st_size
    return total


@contextlib.contextmanager
def exclusive(folder: str | os.PathLike[str], busy: str | None = None) -> Iterator[None]:
    """Hold ``folder``'s lock (an advisory ``flock`` on its ``.lock`` file) for the block.

    ``busy`` None: wait for the lock. For files that several jobs rebuild from what they all write, such as a
    report made from every run present: the jobs take turns, so the last one to write has listed every run written
    before it took the lock, and no job writes over a newer rebuild with an older one. ``busy`` a message: raise it
    as a one-line TnfError at once when another process holds the lock, for work that two processes must never do
    into one folder at the same time (training a run). Where the platform has no ``flock``, the block runs
    unlocked.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # not a POSIX system
        yield
        return
    with open(folder / ".lock", "a") as f:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | (fcntl.LOCK_NB if busy is not None else 0))
        except BlockingIOError:
            raise TnfError(str(busy)) from None
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


@contextlib.contextmanager
def data_seed_claim(root: str | os.PathLike[str], seed: int, what: str) -> Iterator[None]:
    """Hold a claim on the data items of store ``root`` for data seed ``seed`` during the block (``what``: the
    command, for the message another run gets).

    A data item (capture, scene, touches, pairs) sits at one path whatever seed made it, and its key holds the
    seed. Runs that make items of one data seed share them (the jobs of a sweep over shards, the seeds of a sweep
    with ``data_seed`` fixed); a run making another data seed's would replace them under the runs using them. Such
    a run stops at once with a one-line TnfError naming the run that holds the claim.

    The claim is a shared ``flock`` on ``<root>/.data_seed/users.lock``; ``claim.json`` beside it names the seed
    and the runs of the last claim. Where the platform or the file system has no ``flock``, or the store cannot
    be written, the block runs unguarded.
    """
    folder = Path(root) / ".data_seed"
    try:
        import fcntl

        folder.mkdir(parents=True, exist_ok=True)
        users = open(folder / "users.lock", "a")  # noqa: SIM115 (held for the block)
    except (ImportError, OSError) as e:  # not a POSIX system, or a store this run cannot write to
        log.debug("data seed claim in %s not taken: %s", root, e)
        users = None
    if users is None:
        yield
        return
    record = folder / "claim.json"
    me = {"pid": os.getpid(), "host": _host(), "command": what}
    try:
        try:
            with exclusive(folder):  # one claim decided at a time
                try:
                    fcntl.flock(users.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:  # runs hold the store: join them if they use this data seed
                    held = _read_claim(record)
                    runs = [r for r in held["runs"] if _run_alive(r)]
                    if held["seed"] is not None and held["seed"] != seed:
                        names = ", ".join(_run_name(r) for r in runs[-3:])
                        raise TnfError(
                            f"data seed {seed}: another run in {Path(root)} uses the data items of data seed "
                            f"{held['seed']} ({names or 'a run'}), which this run would replace under it. Run the "
                            "seeds one after another, fix data_seed (one dataset for every seed), or give each "
                            "seed its own data_root (docs/cluster.md)"
                        ) from None
                    fcntl.flock(users.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
                    write_json(record, {"seed": seed, "runs": [*runs[-7:], me]})
                else:  # no run holds a claim: the store is ours
                    try:
                        write_json(record, {"seed": seed, "runs": [me]})
                    finally:  # shared from now on, whether or not the record could be written
                        fcntl.flock(users.fileno(), fcntl.LOCK_SH)
        except OSError as e:  # a file system without locks (some network mounts), or a record not written
            log.debug("data seed claim in %s not fully taken: %s", root, e)
        yield
    finally:
        with contextlib.suppress(OSError):
            fcntl.flock(users.fileno(), fcntl.LOCK_UN)  # also for processes forked in the block, which share it
        users.close()


def _run_name(run: dict[str, Any]) -> str:
    return f"`{run.get('command')}` (pid {run.get('pid')} on {run.get('host')})"


def _run_alive(run: dict[str, Any]) -> bool:
    """Whether the run of a claim's record may still be running (runs on other machines cannot be told)."""
    pid, host = run.get("pid"), run.get("host")
    return not isinstance(pid, int) or not isinstance(host, str) or _process_alive(pid, host)


def _read_claim(record: Path) -> dict[str, Any]:
    """The seed (None where unknown) and the runs of a claim's record, whatever the file holds."""
    try:
        held = json.loads(record.read_text())
    except (OSError, ValueError):
        held = None
    if not isinstance(held, dict):
        return {"seed": None, "runs": []}
    seed = held.get("seed")
    runs = held.get("runs")
    return {
        "seed": seed if isinstance(seed, int) else None,
        "runs": [r for r in runs if isinstance(r, dict)] if isinstance(runs, list) else [],
    }


def read_json(path: str | os.PathLike[str], what: str = "file") -> Any:
    """Read JSON, turning a missing or malformed file into a one-line TnfError naming it."""
    path = Path(path)
    try:
        with open(path) as f:
            return json.load(f)
    except FileNotFoundError:
        raise TnfError(f"{what} not found: {path}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise TnfError(f"{what} {path} is not valid JSON: {e}") from None
    except OSError as e:
        raise TnfError(f"cannot read {what} {path}: {e.strerror}") from None


def manifest_record(
    stage: str, item: Sequence[str], config: Mapping[str, Any], info: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """The manifest of a finished item: ``info``, then the stage, the item's path parts, the config that made it
    and its hash (``config_hash``), when, and the tnf and cache versions. Every item's manifest is this record,
    whether the store wrote it (``ArtifactStore.writing``) or a stage finished the item in place (a model run)."""
    return {
        **dict(info or {}),
        "stage": stage,
        "item": list(item),
        "config": _jsonable(config),
        "config_hash": config_hash(config),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "tnf_version": _version(),
        "cache_version": CACHE_VERSION,
    }


class ArtifactStore:
    """Item folders under ``root``, each finished by a manifest that records its config."""

    def __init__(self, root: str | os.PathLike[str] | None = None):
        self.root = data_root(root)

    def path(self, stage: str, *item: str) -> Path:
        return self.root.joinpath(stage, *item)

    def manifest(self, stage: str, *item: str) -> dict[str, Any] | None:
        """The item's manifest, or None when the item is not finished."""
        p = self.path(stage, *item) / MANIFEST
        if not p.is_file():
            return None
        return read_json(p, "manifest")

    def is_done(self, stage: str, *item: str, config: Mapping[str, Any]) -> bool:
        """True when the item is finished and was made with this config."""
        m = self.manifest(stage, *item)
        return m is not None and m.get("config_hash") == config_hash(config)

    def require(self, stage: str, *item: str, hint: str = "") -> Path:
        """The folder of a finished item, or a TnfError saying which stage to run first."""
        p = self.path(stage, *item)
        if not (p / MANIFEST).is_file():
            msg = f"missing {stage} output {p}"
            raise TnfError(msg + (f"; {hint}" if hint else ""))
        return p

    def items(self, stage: str, *prefix: str) -> list[str]:
        """Names of the finished items under ``<stage>/<prefix...>``, sorted: their paths below it, ``/``-joined,
        at any depth (``ball``, or ``mugs/red`` for a nested object name)."""
        base = self.path(stage, *prefix)
        if not base.is_dir():
            return []
        out = [m.parent.relative_to(base).parts for m in base.rglob(MANIFEST)]
        return sorted("/".join(p) for p in out if p and not any(part.startswith(".") for part in p))

    @contextlib.contextmanager
    def writing(
        self, stage: str, *item: str, config: Mapping[str, Any], info: Mapping[str, Any] | None = None
    ) -> Iterator[Path]:
        """Write an item: yields a temporary folder; on success it becomes the item's folder.

        ``info`` (and anything the body stores in the yielded folder's ``manifest.json`` beforehand is
        replaced) goes into the manifest next to the config and its hash. On an exception the temporary
        folder is removed and any earlier finished item is left as it was; a full disk (or quota) becomes a
        one-line ``DiskFull`` naming the item, what was written of it and the space left.
        """
        final = self.path(stage, *item)
        final.parent.mkdir(parents=True, exist_ok=True)
        # A killed earlier write of this item left its temporary folder: remove it, as this write replaces it.
        for stale in final.parent.glob(f".{glob.escape(final.name)}.*.partial"):
            if not _writer_alive(stale):
                shutil.rmtree(stale, ignore_errors=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.{_writer_tag()}.", suffix=".partial", dir=final.parent))
        tmp.chmod(0o777 & ~_umask())  # mkdtemp's folder is private (0700); a finished item is as readable as its store
        extra: dict[str, Any] = {}
        try:
            yield tmp
            extra_path = tmp / MANIFEST
            if extra_path.is_file():  # the body may leave fields for the manifest
                extra = read_json(extra_path, "manifest")
            write_json(tmp / MANIFEST, manifest_record(stage, item, config, {**extra, **dict(info or {})}))
            _replace_dir(tmp, final)
        except BaseException as e:
            full = _disk_full(e)
            written = _tree_bytes(tmp) if full else 0
            shutil.rmtree(tmp, ignore_errors=True)
            if full:
                raise DiskFull(
                    f"{_reason(e)} writing {final}: {_mb(written)} MB were written into the item before the disk "
                    f"filled; free space there: {_mb(free_bytes(final.parent))} MB",
                    item=True,
                ) from None
            raise

    def clean_partials(self, stage: str, *item: str) -> int:
        """Remove temporary folders that interrupted runs left below ``stage[/item...]``; returns how many.

        Folders that a running process is still writing (parallel jobs sharing the store) are kept.
        """
        base = self.path(stage, *item)
        n = 0
        if base.is_dir():
            for p in list(base.rglob(".*.partial")):
                if _writer_alive(p):
                    continue
                shutil.rmtree(p, ignore_errors=True)
                n += 1
        return n


# Temporary item folders and files are named ``.<name>.<pid>@<host>.<random>.partial`` (``.tmp``) so that
# cleaning can tell a killed writer's leftovers from what another job on this machine is writing right now.
_TEMPORARY = re.compile(r"\.(\d+)@([A-Za-z0-9-]+)\.[^.]*\.(partial|tmp)$")


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname().split(".")[0]) or "host"


def _writer_tag() -> str:
    return f"{os.getpid()}@{_host()}"


def _writer_alive(temporary: Path) -> bool:
    """Whether the process that created the temporary folder or file ``temporary`` may still be writing it."""
    m = _TEMPORARY.search(temporary.name)
    if m is None:  # no writer in its name: not a write in progress
        return False
    return _process_alive(int(m[1]), m[2])


def _process_alive(pid: int, host: str) -> bool:
    """Whether process ``pid`` of machine ``host`` may still run (another machine's cannot be told: True)."""
    if host != _host() or pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # a live process of another user
        return True
    return True


def files_digest(folder: Path, skip: str | None = None) -> str:
    """A hash of the names, sizes and modification times of every file under ``folder`` (except the
    sub-folder ``skip``), without reading them: it changes when any file is written again."""
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        rel = p.relative_to(folder)
        if not p.is_file() or (skip is not None and rel.parts[0] == skip):
            continue
        st = p.stat()
        h.update(f"{rel.as_posix()}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()[:16]


@functools.cache
def _umask() -> int:
    """The process's file-mode creation mask (read once, by setting it and setting it back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _replace_dir(src: Path, dst: Path) -> None:
    """Move folder ``src`` to ``dst``, replacing an old ``dst`` with as short a gap as a rename allows.

    Other processes may replace the same item at the same moment (two jobs of a sweep that make the same
    item): each attempt either renames ``src`` into place whole or finds a ``dst`` in the way, moves that aside
    and tries again. Every writer finishes, and the item ends as one writer's complete folder (the last one's).
    """
    aside: list[Path] = []
    try:
        for _ in range(100):
            try:
                os.rename(src, dst)  # fails while a (non-empty) dst exists
                return
            except OSError as e:
                if e.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                    raise
            # Named like a temporary folder, so that a writer killed right here leaves something cleaning removes.
            old = dst.with_name(f".{dst.name}.{_writer_tag()}.{uuid.uuid4().hex[:8]}.partial")
            try:
                os.rename(dst, old)
                aside.append(old)
            except FileNotFoundError:
                pass  # another writer moved it aside first
        raise TnfError(f"cannot put {dst} in place: other processes keep replacing it")
    finally:
        for old in aside:
            shutil.rmtree(old, ignore_errors=True)


def _version() -> str:

    return __version__


# Each stage's folder in the store, by the stage's command name.
STAGE_FOLDERS = {
    "capture": "capture",
    "fit-scene": "scenes",
    "touch": "touch",
    "pair": "pairs",
    "train": "models",
    "generate": "generated",
}


def clean(args: list[str]) -> str:
    """``tnf clean STAGE [ITEM] [data_root=DIR]``: remove the finished item ``<data_root>/<folder>/ITEM`` (a path
    such as ``digit/builtin/ball`` for a touch item) so that the next run of its stage redoes it; without ITEM,
    list the stage's finished items. STAGE is a stage's command (``fit-scene``) or its folder (``scenes``).
    Returns what was done, as text."""
    root_arg = [a for a in args if a.startswith("data_root=")]
    rest = [a for a in args if not a.startswith("data_root=")]
    store = ArtifactStore(root_arg[-1].split("=", 1)[1] if root_arg else None)
    if not rest or len(rest) > 2:
        raise TnfError("usage: tnf clean STAGE [ITEM] [data_root=DIR], e.g. tnf clean touch digit/builtin/ball")
    commands = {folder: command for command, folder in STAGE_FOLDERS.items()}
    if rest[0] not in STAGE_FOLDERS and rest[0] not in commands:
        raise TnfError(f"tnf clean: no stage {rest[0]!r}; stages: {', '.join(STAGE_FOLDERS)}")
    folder = STAGE_FOLDERS.get(rest[0], rest[0])
    stage = commands[folder]
    base = store.path(folder)
    if not base.is_dir():
        raise TnfError(f"no {stage} items: {base} does not exist")
    if len(rest) == 1:
        found = sorted(str(m.parent.relative_to(base)) for m in base.rglob(MANIFEST))
        return "\n".join(found) if found else f"{base}: no finished items"
    parts = Path(rest[1]).parts
    if not parts or any(p in ("..", ".") or p.startswith("/") for p in parts):
        raise TnfError(f"item must be a path inside {base}, got {rest[1]!r}")
    item = base.joinpath(*parts)
    if not (item / MANIFEST).is_file():
        raise TnfError(f"{item} is not a finished item (no {MANIFEST}); `tnf clean {stage}` lists them")
    shutil.rmtree(item)
    return f"removed {item}; `tnf {stage}` with its settings redoes it"
