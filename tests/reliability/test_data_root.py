"""Where data goes: a data root that is a file, lies under a file or in an unwritable place, and a disk that is
or becomes full, through the real `tnf` command. Each is refused as one `error:` line naming the path and what is
wrong, exit code 1, and leaves nothing that looks finished (no Hydra run folder, no manifest, no temporary item).

The full-disk tests mount a small tmpfs (root, or a container that allows mounts) and are skipped where that
is not allowed."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.reliability.helpers import QUIET, finished_items, leftovers

# 240x320 Digit frames: a touch's PNG is ~130 KB, the background's at the same compression ~100 KB.
BIG_FRAMES = ["sensor.width=240", "sensor.height=320"]


def run_lines(capsys, *args: str) -> tuple[int, list[str]]:
    """``tnf ARGS`` in this process: (exit code, the non-empty lines of stderr)."""
    from tnf.cli import main

    capsys.readouterr()
    rc = main([*args])
    return rc, [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]


def assert_one_line(lines: list[str], *words: str) -> str:
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


def no_logs_under(folder: Path) -> None:
    """Hydra did not get as far as making its run folder anywhere under ``folder``."""
    assert [p for p in folder.rglob("logs")] == []


@contextlib.contextmanager
def tmpfs(path: Path, options: str):
    """``path`` as a fresh tmpfs mounted with ``options``; skips the test where mounting is not allowed."""
    path.mkdir(parents=True, exist_ok=True)
    if shutil.which("mount") is None:
        pytest.skip("no mount command")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


# -- the data root itself ---------------------------------------------------------------------------------
@pytest.mark.parametrize("how", ["override", "TNF_DATA"])
def test_data_root_that_is_a_file(capsys, tmp_path, monkeypatch, how):
    file = tmp_path / "afile"
    file.write_text("not a folder")
    if how == "override":
        monkeypatch.setenv("TNF_DATA", str(tmp_path / "elsewhere"))
        rc, lines = run_lines(capsys, "objects", f"data_root={file}")
    else:
        monkeypatch.setenv("TNF_DATA", str(file))
        rc, lines = run_lines(capsys, "objects")
    assert rc == 1
    assert_one_line(lines, str(file), "is a file, not a folder")
    assert file.read_text() == "not a folder"
    no_logs_under(tmp_path)
    assert not (tmp_path / "elsewhere").exists()


def test_data_root_under_a_file(capsys, tmp_path, monkeypatch):
    file = tmp_path / "afile"
    file.write_text("x")
    monkeypatch.setenv("TNF_DATA", str(tmp_path / "elsewhere"))
    rc, lines = run_lines(capsys, "objects", f"data_root={file}/sub/deeper")
    assert rc == 1
    assert_one_line(lines, f"{file}/sub/deeper", f"{file} is a file")
    no_logs_under(tmp_path)


def test_logs_folder_that_is_a_file(capsys, tmp_path):
    root = tmp_path / "root"
    root.mkdir()
    (root / "logs").write_text("x")
    rc, lines = run_lines(capsys, "objects", f"data_root={root}")
    assert rc == 1
    assert_one_line(lines, str(root / "logs"), "is a file")


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root writes into read-only folders")
def test_data_root_in_a_folder_without_write_permission(capsys, tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    try:
        rc, lines = run_lines(capsys, "objects", f"data_root={locked}/x")
        assert rc == 1
        assert_one_line(lines, f"{locked}/x", "not writable")
        assert not (locked / "x").exists()
    finally:
        locked.chmod(0o700)


def test_data_root_where_not_even_root_can_make_folders(capsys, tmp_path, monkeypatch):
    """/proc takes no new entries, whoever asks (os.access says writable to root)."""
    if not Path("/proc/self").is_dir() or Path("/proc/tnf-data").exists():
        pytest.skip("no Linux /proc")
    monkeypatch.setenv("TNF_DATA", str(tmp_path / "elsewhere"))
    rc, lines = run_lines(capsys, "objects", "data_root=/proc/tnf-data")
    assert rc == 1
    assert_one_line(lines, "/proc/tnf-data", "cannot be created")
    no_logs_under(tmp_path)


def test_data_root_on_a_read_only_file_system(capsys, tmp_path):
    with tmpfs(tmp_path / "ro", "size=1m,ro") as ro:
        for root in (ro, ro / "x"):  # an existing folder, and one to be made there
            rc, lines = run_lines(capsys, "objects", f"data_root={root}")
            assert rc == 1
            assert_one_line(lines, str(root), "read-only file system")
        assert list(ro.iterdir()) == []


def test_help_and_cfg_still_work_with_a_bad_data_root(capsys, tmp_path):
    """Hydra only prints for these: nothing is written, so the data root is not checked."""
    file = tmp_path / "afile"
    file.write_text("x")
    from tnf.cli import main

    assert main(["objects", f"data_root={file}", "--cfg", "job"]) == 0
    assert f"data_root: {file}" in capsys.readouterr().out


# -- full disks -------------------------------------------------------------------------------------------
def test_nearly_full_data_root_is_refused_before_hydra_writes(capsys, tmp_path):
    with tmpfs(tmp_path / "disk", "size=1m") as disk:
        (disk / "filler").write_bytes(b"\0" * 900_000)
        rc, lines = run_lines(capsys, "objects", f"data_root={disk}")
        assert rc == 1
        assert_one_line(lines, str(disk), "no space left", "MB free")
        assert not (disk / "logs").exists()


def test_touch_refuses_an_item_that_cannot_fit(capsys, tmp_path):
    """200+ Digit frames need ~20 MB: refused before simulating, naming what is needed and what is free."""
    with tmpfs(tmp_path / "disk", "size=2m") as disk:
        rc, lines = run_lines(
            capsys, "touch", *QUIET, "object_names=[ball]", f"data_root={disk}", *BIG_FRAMES, "touch.n_touches=200"
        )
        assert rc == 1
        line = assert_one_line(lines, "not enough space", str(disk / "touch" / "digit" / "builtin" / "ball"), "MB")
        needed, free = (float(x) for x in re.findall(r"([\d.]+) MB", line))
        assert needed > 15 and free <= 2.2, line
        assert finished_items(disk, "touch") == [] and leftovers(disk) == []


def test_disk_that_fills_while_touch_writes(capsys, tmp_path):
    """40 Digit frames pass the up-front estimate (~4.1 MB) on a 4.7 MB disk but take ~5.4 MB: the disk fills
    while the image writer threads write. One line, how much was written, no finished item, no temporary folder."""
    with tmpfs(tmp_path / "disk", "size=4600k") as disk:
        rc, lines = run_lines(
            capsys, "touch", *QUIET, "object_names=[ball]", f"data_root={disk}", *BIG_FRAMES, "touch.n_touches=32"
        )
        assert rc == 1
        item = disk / "touch" / "digit" / "builtin" / "ball"
        line = assert_one_line(lines, "no space left on device", str(item), "were written into the item")
        written, free = (float(x) for x in re.findall(r"([\d.]+) MB", line))
        assert 3.0 < written <= 4.7 and free > 3.0, line  # the partial item was removed again
        assert not item.exists()
        assert finished_items(disk, "touch") == [] and leftovers(disk) == []
        assert list(disk.rglob("manifest.json")) == []


def test_write_bytes_on_a_full_disk_is_one_line(tmp_path):
    from tnf.artifacts import DiskFull, write_bytes

    with tmpfs(tmp_path / "disk", "size=1m") as disk:
        with pytest.raises(DiskFull) as e:
            write_bytes(disk / "big.bin", b"\1" * 2_000_000)
        msg = str(e.value)
        assert "\n" not in msg and str(disk / "big.bin") in msg and "2.0 MB" in msg, msg
        assert list(disk.iterdir()) == []  # neither the file nor its temporary file
