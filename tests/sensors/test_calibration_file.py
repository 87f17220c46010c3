"""A calibration file that cannot be read (truncated, corrupt, not an archive) is one line naming it, from
``load_calibration`` and through the ``tnf`` command."""

import subprocess
import sys

import numpy as np
import pytest

from tests.sensors.calibrations import random_calibration
from tnf.errors import TnfError
from tnf.sensors.calibration import FILE, load_calibration


@pytest.fixture
def saved(tmp_path):
    """A valid calibration folder for a 320x240 sensor, as ``tnf calibrate`` writes it."""
    cal = random_calibration()
    folder = tmp_path / "cal"
    cal.save(folder)
    assert load_calibration(folder).digest() == cal.digest()
    return folder


def _one_line(folder):
    with pytest.raises(TnfError, match=r"^sensor calibration .*calibration\.npz is not readable \(") as e:
        load_calibration(folder)
    msg = str(e.value)
    assert "\n" not in msg and str(folder / FILE) in msg
    return msg


@pytest.mark.parametrize("keep", [0.02, 0.5, 0.99])
def test_truncated_calibration_is_one_line(saved, keep):
    data = (saved / FILE).read_bytes()
    (saved / FILE).write_bytes(data[: int(keep * len(data))])
    _one_line(saved)


def test_corrupt_member_is_one_line(saved):
    data = bytearray((saved / FILE).read_bytes())
    mid = len(data) // 2  # inside the background's bytes: the archive opens, the member fails its CRC
    data[mid : mid + 64] = bytes(64)
    (saved / FILE).write_bytes(bytes(data))
    _one_line(saved)


@pytest.mark.parametrize("content", [b"", b"garbage", b"\x80\x04\x95garbage", b"PK\x03\x04" + bytes(40)])
def test_garbage_calibration_is_one_line(saved, content):
    (saved / FILE).write_bytes(content)
    _one_line(saved)


def test_a_single_array_is_not_a_calibration(saved):
    with open(saved / FILE, "wb") as f:
        np.save(f, np.zeros((9, 9, 3), np.float32))
    assert "not an .npz archive" in _one_line(saved)


def test_cli_reports_a_corrupt_calibration_in_one_line(saved, tmp_path):
    data = (saved / FILE).read_bytes()
    (saved / FILE).write_bytes(data[: len(data) // 2])
    args = ["touch", "debug=tiny", "sensor=gelsight_mini", f"sensor.calibration={saved}", f"data_root={tmp_path}/d"]
    out = subprocess.run([sys.executable, "-m", "tnf.cli", *args], capture_output=True, text=True)
    assert out.returncode == 1
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr
    assert lines[0].startswith(f"error: sensor calibration {saved / FILE} is not readable (")


@pytest.mark.parametrize(
    "change, pattern",
    [
        ({"background": lambda b: b[..., 0]}, r"background must be an \[H, W, 3\] uint8 image, got \[240, 320\] uint8"),
        ({"background": lambda b: b.astype(np.float64) * 2}, r"background must be an .* got \[240, 320, 3\] float64"),
        ({"falloff": lambda f: np.inf}, r"falloff must be > 0, blur_sigma and noise_std >= 0, all finite"),
    ],
)
def test_foreign_values_are_one_line(saved, change, pattern):
    """A background of another shape or type, or a number that is not finite: refused, not silently converted."""
    with np.load(saved / FILE) as d:
        arrays = {k: d[k] for k in d.files}
    for key, edit in change.items():
        arrays[key] = edit(arrays[key])
    np.savez(saved / FILE, **arrays)
    with pytest.raises(TnfError, match=pattern) as e:
        load_calibration(saved)
    assert "\n" not in str(e.value)
