"""Corrupt artifacts are named before a stage works or writes, and `tnf clean` makes a stage redo an item."""

import pytest

from tnf.cli import main
from tnf.data.render import TouchItem
from tnf.errors import TnfError


@pytest.fixture
def touched(tmp_path, monkeypatch):
    """A real touch item of the built-in ball (debug scale) in a fresh store."""
    monkeypatch.setenv("TNF_DATA", str(tmp_path))
    assert main(["touch", "debug=tiny", "object_names=[ball]", "progress=false"]) == 0
    return tmp_path / "touch" / "digit" / "builtin" / "ball"


def test_a_truncated_touch_image_is_named_when_the_item_is_opened(touched):
    TouchItem.load(touched)  # whole: opens
    png = sorted((touched / "images").glob("*.png"))[3]
    data = png.read_bytes()
    png.write_bytes(data[: len(data) // 2])
    with pytest.raises(TnfError, match=rf"{png.name} is not a readable image .*tnf clean touch") as e:
        TouchItem.load(touched)
    assert "\n" not in str(e.value)


def test_a_truncated_dataset_array_stops_training_before_the_run_folder(tmp_path, monkeypatch, capsys):
    from tests.generators.test_stages import write_pairs

    monkeypatch.setenv("TNF_DATA", str(tmp_path))
    write_pairs(tmp_path / "pairs" / "digit-hashgrid", n=9)
    f = tmp_path / "pairs" / "digit-hashgrid" / "tactile.npy"
    f.write_bytes(f.read_bytes()[:1000])
    assert main(["train", "train.epochs=1", "progress=false"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "tactile.npy is not a readable array" in err[0]
    assert not (tmp_path / "models").exists()


def test_clean_removes_a_finished_item_and_the_stage_redoes_it(touched, capsys):
    root = touched.parents[3]
    assert main(["clean", "touch"]) == 0
    assert capsys.readouterr().out.strip() == "digit/builtin/ball"
    assert main(["clean", "touch", "digit/builtin/ball"]) == 0
    assert capsys.readouterr().out.strip().endswith("; `tnf touch` with its settings redoes it")
    assert not touched.exists()
    for bad in (["clean", "touch", "digit/builtin/ball"], ["clean", "touch", "../capture"], ["clean", "nope", "x"]):
        assert main(bad) == 1
        assert len(capsys.readouterr().err.strip().splitlines()) == 1
    # A stage's command or its folder; the message names the command that redoes the item.
    assert main(["clean", "fit-scene"]) == 1
    assert capsys.readouterr().err.strip() == f"error: no fit-scene items: {root / 'scenes'} does not exist"
    assert main(["clean", "nope"]) == 1
    assert "stages: capture, fit-scene, touch, pair, train, generate" in capsys.readouterr().err
    assert main(["clean", "scenes"]) == 1  # the folder's name says the same
    assert capsys.readouterr().err.strip() == f"error: no fit-scene items: {root / 'scenes'} does not exist"
    assert main(["touch", "debug=tiny", "object_names=[ball]", "progress=false"]) == 0
    assert (touched / "manifest.json").is_file() and root.exists()
