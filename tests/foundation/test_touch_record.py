"""The touch record: its JSON round trip keeps keys, order and values, and a malformed entry is refused."""

import json

import numpy as np
import pytest

from tnf.errors import TnfError
from tnf.touches import TouchRecord, as_matrix, as_point, read_touch_records, touch_records_of

POSE = np.array([[1.0, 0, 0, 0.1], [0, 1, 0, 0.02], [0, 0, 1, 0.3], [0, 0, 0, 1]])

SIMULATED = {
    "index": 3,
    "split": "val",
    "image": "images/00003.png",
    "start_c2w": POSE.tolist(),
    "contact_c2w": (POSE * 0.5).tolist(),
    "contact_point": [0.1, 0.02, 0.012345678901234567],
    "force": 4.5,
    "penetration": 0.0007,
    "force_target": 5.0,
    "force_band": "interpolation",
}
IMPORTED = {k: SIMULATED[k] for k in ("index", "split", "image", "start_c2w", "contact_c2w", "contact_point")} | {
    "force": None,
    "penetration": None,
}
GENERATED = {k: SIMULATED[k] for k in ("index", "split", "image", "start_c2w")} | {
    "contact_point": None,
    "force": 2.0,
    "penetration": None,
    "pose_index": 1,
}


@pytest.mark.parametrize("entry", [SIMULATED, IMPORTED, GENERATED], ids=["simulated", "imported", "generated"])
def test_round_trip_is_byte_identical(entry):
    record = TouchRecord.from_json(json.loads(json.dumps(entry)), "m.json", 0)
    assert json.dumps(record.to_json()) == json.dumps(entry)  # same keys, order and values
    assert TouchRecord.from_json(record.to_json(), "m.json", 0) == record


def test_built_from_arrays_writes_what_tolist_writes():
    record = TouchRecord(
        index=0,
        split="train",
        image="images/00000.png",
        start_c2w=as_matrix(POSE),
        contact_point=as_point(POSE[:3, 3].astype(np.float32)),
        force=1.0,
    )
    out = record.to_json()
    assert out["start_c2w"] == POSE.tolist() and out["contact_point"] == POSE[:3, 3].astype(np.float32).tolist()
    assert list(out) == ["index", "split", "image", "start_c2w", "contact_point", "force", "penetration"]


def test_reader_gives_records(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps({"object": "ball", "touches": [SIMULATED, GENERATED]}))
    records = read_touch_records(tmp_path)
    assert [r.index for r in records] == [3, 3] and records[0].force_band == "interpolation"
    assert np.asarray(records[0].start_c2w).shape == (4, 4) and records[1].contact_c2w is None


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"start_c2w": [[1, 0, 0]]}, "start_c2w must be a finite 4x4 matrix"),
        ({"start_c2w": None}, "start_c2w must be a finite 4x4 matrix"),
        ({"contact_c2w": [[float("nan")] * 4] * 4}, "contact_c2w must be a finite 4x4 matrix"),
        ({"contact_point": [0, 0]}, "contact_point must be 3 numbers"),
        ({"index": "3"}, "'index' must be an integer"),
        ({"index": True}, "'index' must be an integer"),
        ({"split": 1}, "'image' and 'split' must be strings"),
        ({"force": "5 N"}, "'force' must be a number or null"),
        ({"force_band": 2}, "'force_band' must be a string"),
        ({"pose_index": 1.5}, "'pose_index' must be an integer"),
        ({"image": "<delete>"}, "lacks 'image'"),
    ],
)
def test_malformed_entry_is_refused(tmp_path, change, message):
    entry = {k: v for k, v in SIMULATED.items() if change.get(k) != "<delete>"}
    entry |= {k: v for k, v in change.items() if v != "<delete>"}
    path = tmp_path / "manifest.json"
    path.write_text(json.dumps({"touches": [SIMULATED, entry]}))
    with pytest.raises(TnfError) as e:
        read_touch_records(tmp_path)
    text = str(e.value)
    assert "\n" not in text and str(path) in text and "touch 1" in text and message in text, text


@pytest.mark.parametrize("manifest", [[], {"touches": {}}, {"object": "ball"}, None])
def test_manifest_without_a_touch_list_is_refused(manifest):
    with pytest.raises(TnfError, match="has no 'touches' list"):
        touch_records_of(manifest, "somewhere/manifest.json")
    with pytest.raises(TnfError, match="touch 0 is not an object"):
        touch_records_of({"touches": [7]}, "somewhere/manifest.json")
