"""Settings that would allocate more memory than the machine has are refused up front, naming the figure."""

import pytest

from tnf.cli import main
from tnf.errors import TnfError
from tnf.runtime import available_memory, check_memory


def test_check_memory_refuses_more_than_is_available():
    have = available_memory()
    if have is None:
        pytest.skip("this platform does not report available memory")
    check_memory(0.1 * have, "small work", "x=1")  # fits: no error
    with pytest.raises(TnfError, match=r"^big work would need about [\d.]+ GiB of memory \(x=2\); this machine has"):
        check_memory(2.0 * have, "big work", "x=2")


@pytest.mark.parametrize("size", [20000, 100000])
def test_a_huge_sensor_is_refused_before_anything_is_allocated(size, capsys, tmp_path, monkeypatch):
    if available_memory() is None:
        pytest.skip("this platform does not report available memory")
    monkeypatch.setenv("TNF_DATA", str(tmp_path))
    args = ["touch", "debug=tiny", "object_names=[ball]", "progress=false", f"sensor.width={size}"]
    assert main([*args, f"sensor.height={size}"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "GiB of memory" in err[0] and f"sensor.width={size}, sensor.height={size}" in err[0]
    assert not (tmp_path / "touch").exists()  # nothing written


def test_an_allocation_no_estimate_caught_is_one_line_naming_its_size(capsys, tmp_path, monkeypatch):
    monkeypatch.setenv("TNF_DATA", str(tmp_path))
    args = ["capture", "debug=tiny", "object_names=[ball]", "progress=false", "capture.num_views=10000000000"]
    assert main(args) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: tnf capture ran out of memory asking for"), err
    assert not list(tmp_path.rglob("manifest.json"))


@pytest.mark.parametrize(
    "stage, overrides, setting",
    [
        ("fit-scene", ["fit.batch_rays=100000000000"], "fit.batch_rays=100000000000"),
        ("pair", ["pair.render_batch=100000", "pair.render_px=4096"], "pair.render_batch=100000, pair.render_px=4096"),
        ("train", ["data.batch_size=100000000"], "data.batch_size=100000000"),
        ("generate", ["generate.batch_size=1000000000"], "generate.batch_size=1000000000"),
        ("pipeline", ["-m", "data.batch_size=16,100000000"], "data.batch_size=100000000"),
    ],
)
def test_size_settings_beyond_memory_are_refused_before_anything_runs(
    stage, overrides, setting, capsys, tmp_path, monkeypatch
):
    if available_memory() is None:
        pytest.skip("this platform does not report available memory")
    monkeypatch.setenv("TNF_DATA", str(tmp_path))
    assert main([stage, *overrides]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "GiB of memory" in err[0] and f"({setting})" in err[0], err
    assert list(tmp_path.iterdir()) == []  # refused before Hydra's run folder
