import json
import os

import pytest

from tnf import TnfError
from tnf.artifacts import ArtifactStore, _umask, config_hash, data_root, read_json, write_json


def test_data_root_precedence(tmp_path, monkeypatch):
    monkeypatch.delenv("TNF_DATA", raising=False)
    monkeypatch.chdir(tmp_path)
    assert data_root() == tmp_path / "tnf-data"
    monkeypatch.setenv("TNF_DATA", str(tmp_path / "env"))
    assert data_root() == tmp_path / "env"
    assert data_root(str(tmp_path / "cfg")) == tmp_path / "cfg"


def test_config_hash_ignores_key_order():
    assert config_hash({"a": 1, "b": [1, 2]}) == config_hash({"b": [1, 2], "a": 1})
    assert config_hash({"a": 1}) != config_hash({"a": 2})


def test_item_written_atomically_and_skipped_when_config_matches(tmp_path):
    store = ArtifactStore(tmp_path)
    cfg = {"views": 48}
    assert not store.is_done("capture", "builtin", "ball", config=cfg)
    with store.writing("capture", "builtin", "ball", config=cfg, info={"n": 3}) as tmp:
        (tmp / "a.txt").write_text("hello")
        # nothing is visible under the final name while the item is being written
        assert not store.path("capture", "builtin", "ball").exists()
    item = store.path("capture", "builtin", "ball")
    assert (item / "a.txt").read_text() == "hello"
    m = store.manifest("capture", "builtin", "ball")
    assert m["n"] == 3 and m["config"] == cfg and m["config_hash"] == config_hash(cfg)
    assert store.is_done("capture", "builtin", "ball", config=cfg)
    assert not store.is_done("capture", "builtin", "ball", config={"views": 12})
    assert store.items("capture") == ["builtin/ball"]


def test_a_finished_item_is_as_readable_as_its_store(tmp_path):
    """A shared store (docs/cluster.md): under umask 022 a finished item's folder is 0755, as its parent is, not
    the private 0700 of a temporary folder."""
    store = ArtifactStore(tmp_path)
    with store.writing("capture", "builtin", "ball", config={}) as tmp:
        (tmp / "a.txt").write_text("hello")
    item = store.path("capture", "builtin", "ball")
    assert item.stat().st_mode & 0o777 == item.parent.stat().st_mode & 0o777 == 0o777 & ~_umask()
    assert item.stat().st_mode & 0o077 == 0o077 & ~_umask()


def test_failed_write_leaves_old_item_and_no_partial(tmp_path):
    store = ArtifactStore(tmp_path)
    with store.writing("touch", "x", config={"v": 1}) as tmp:
        (tmp / "data").write_text("old")
    with pytest.raises(RuntimeError):
        with store.writing("touch", "x", config={"v": 2}) as tmp:
            (tmp / "data").write_text("half")
            raise RuntimeError("killed")
    assert (store.path("touch", "x") / "data").read_text() == "old"
    assert store.is_done("touch", "x", config={"v": 1})
    assert sorted(os.listdir(store.path("touch"))) == ["x"]


def test_rewrite_replaces_item(tmp_path):
    store = ArtifactStore(tmp_path)
    for v in (1, 2):
        with store.writing("touch", "x", config={"v": v}) as tmp:
            (tmp / f"f{v}").write_text(str(v))
    assert sorted(p.name for p in store.path("touch", "x").iterdir()) == ["f2", "manifest.json"]


def test_partials_of_killed_runs_are_not_items(tmp_path):
    store = ArtifactStore(tmp_path)
    (store.path("scenes") / ".ball.abc.partial").mkdir(parents=True)
    assert store.items("scenes") == []
    assert store.clean_partials("scenes") == 1


def test_require_and_json_errors(tmp_path):
    store = ArtifactStore(tmp_path)
    with pytest.raises(TnfError, match="missing scenes output .*ball; run tnf fit-scene"):
        store.require("scenes", "ball", hint="run tnf fit-scene")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(TnfError, match="manifest .*bad.json is not valid JSON"):
        read_json(bad, "manifest")
    with pytest.raises(TnfError, match="manifest not found"):
        read_json(tmp_path / "none.json", "manifest")


def test_write_json_leaves_no_temporary_files(tmp_path):
    write_json(tmp_path / "m.json", {"a": 1})
    assert json.loads((tmp_path / "m.json").read_text()) == {"a": 1}
    assert os.listdir(tmp_path) == ["m.json"]


def test_written_files_are_readable_like_plain_files(tmp_path):
    write_json(tmp_path / "m.json", {"a": 1})
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "m.json").stat().st_mode & 0o777 == 0o666 & ~umask
